"""EtherCAT slaves on a network interface, for ``rtloop io list --ethercat IF``.

SOEM (pysoem) enumerates the segment and reads each slave's identity from its SII, and whether
its SII describes a distributed clocks mode (rtloop runs it on DC then); what stops a
scan (no such interface, the interface down, no raw-socket permission, pysoem missing, nothing
answering) is one entry with its fix.
"""

from __future__ import annotations

from typing import Any

from rtloop.io.drives.rawsocket import RAW_SOCKET_PERMISSION, interface_problem, open_raw
from rtloop.io.drives.sii import parse_sii
from rtloop.io.inventory import Interface

__all__ = ["ethercat_slaves"]

_STATES = {1: "INIT", 2: "PRE-OP", 3: "BOOT", 4: "SAFE-OP", 8: "OP"}


def ethercat_slaves(interface: str) -> list[Interface]:
    problem = interface_problem(interface)
    if problem:
        fix = problem.rpartition(": ")[2] if "down" in problem else "ip link show (the port the drives hang on)"
        return [Interface("ethercat", interface, problem, False, fix)]
    try:
        open_raw(interface).close()
    except PermissionError:
        return [Interface("ethercat", interface, "no permission for a raw socket", False,
                          RAW_SOCKET_PERMISSION)]
    except OSError as error:
        return [Interface("ethercat", interface, f"cannot open it raw: {error.strerror}", False, "")]
    try:
        import pysoem  # type: ignore[import-untyped]  # pysoem ships no type information
    except ImportError:
        return [Interface("ethercat", interface, "pysoem is not installed", False, "pip install 'rtloop[ethercat]'")]
    master = pysoem.Master()
    try:
        master.open(interface)
        found = master.config_init()
        if found <= 0:
            return [Interface("ethercat", interface, "no EtherCAT slave answered", False,
                              "power and cable the drives to this port (emulated: rtloop io emulate ethercat)")]
        master.read_state()
        return [Interface("ethercat", f"{interface} slave {position}",
                          f"{slave.name}: vendor 0x{slave.man:08X}, product 0x{slave.id:08X}, revision "
                          f"0x{slave.rev:08X}, {_STATES.get(slave.state & 0x0F, hex(slave.state))}, "
                          f"{_clocks(slave)}", True)
                for position, slave in enumerate(master.slaves, start=1)]
    finally:
        master.close()


def _clocks(slave: Any) -> str:
    """Whether the slave's SII describes a distributed clocks mode (category 60)."""
    try:
        assign = parse_sii(lambda word: bytes(slave.eeprom_read(word))).dc_assign_activate
    except Exception:  # an SII that does not read: the listing goes on without it
        return "distributed clocks unknown (its SII did not read)"
    return f"distributed clocks (AssignActivate 0x{assign:04X})" if assign else "no distributed clocks"
