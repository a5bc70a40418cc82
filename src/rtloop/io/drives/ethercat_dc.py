"""Distributed clocks (DC) for the EtherCAT drive device: which slaves run on them, the reference
clock's time in every cycle's frame, and SYNC0 started on a release of rtloop's timeline.

What a master does, as ETG.1000 and the ESC datasheets describe it (and SOEM's ``ec_configdc``,
through pysoem's ``config_dc``, does the first part): latch every slave's receive times with a
broadcast write to 0x0900, work out each slave's propagation delay (0x0928) and the offset of its
local clock (0x0920) so that every slave's system time (0x0910) reads the same, in ns since
2000-01-01 (SOEM sets it from the master's wall clock). The first slave with DC is the reference
clock: every cycle's frame carries an FRMW datagram after its LRW that reads the reference's
system time and writes it into every other DC slave, whose drift control follows it.

rtloop's timeline is CLOCK_MONOTONIC. At T0's announcement (``start_sync0``) the reference's system
time is read between two readings of CLOCK_MONOTONIC: their midpoint maps a monotonic instant onto
the DC system time (``offset_ns``), and SYNC0 of each slave rtloop runs on DC starts at the first
release T0 + kP at least ``SYNC0_LEAD_NS`` ahead, mapped, with the period as its cycle time.
"""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from rtloop.io.drives.joints import JointConfig
from rtloop.io.drives.rawsocket import new_frame, put_datagram

__all__ = [
    "DC_INDEX",
    "FRMW",
    "REG_SYSTEM_TIME",
    "SYNC0_LEAD_NS",
    "DcPlan",
    "dc_plan",
    "first_release",
    "has_dc_unit",
    "measure_slide",
    "read_system_time",
    "start_on_release",
    "start_sync0",
    "station",
]

FPRD, FPWR, FRMW = 4, 5, 14
REG_SYSTEM_TIME = 0x0910
REG_CYCLIC_CONTROL, REG_SYNC0_START, REG_SYNC0_CYCLE = 0x0980, 0x0990, 0x09A0
DC_INDEX = 0x5C
"""The datagram index of the DC set-up frames (the cycle's frame counts its own)."""
SYNC0_LEAD_NS = 20_000_000
"""SYNC0's first pulse is at least this far ahead of its set-up (a start time already past would
wait for the slave's 32-bit clock to come round: about 4 s)."""
MAX_SYNC0_CYCLE_NS = 0xFFFFFFFF
DATA_AT = 26


def station(position: int) -> int:
    """The configured station address SOEM gives the slave at ``position`` (from 1)."""
    return 0x1000 + position


@dataclass
class DcPlan:
    """How each slave runs: on DC (SYNC0 started by rtloop) or free on the frames, and why."""

    reference: int = 0
    """The position of the reference clock (the first slave with DC); 0: no slave has DC."""
    with_dc: int = 0
    """Slaves that have DC: the working counter of the cycle's FRMW (the reference reads, each other writes)."""
    synced: dict[int, int] = field(default_factory=dict)
    """Slave position → the AssignActivate rtloop writes to 0x0980 (from its SII) to start SYNC0."""
    free: dict[int, str] = field(default_factory=dict)
    """Slave position → why it runs free on the frames."""
    offset_ns: int = 0
    """DC system time − CLOCK_MONOTONIC, as read from the reference clock at SYNC0's start."""
    mapped_at_ns: int = 0
    """When (CLOCK_MONOTONIC) that mapping was read; 0: SYNC0 not started."""
    uncertainty_ns: int = 0
    """Half that read's round trip: how far the mapping may be off."""
    sync0: str = ""
    """Where SYNC0 started, for the run's note."""
    slide: str = ""
    """How far SYNC0 slid against the releases over the run (the reference clock's drift), for the note."""

    def describe(self, joints: Sequence[JointConfig]) -> list[str]:
        sync0 = self.sync0
        lines = []
        for joint in joints:
            who = f"joint {joint.name!r} (slave {joint.slave})"
            if joint.slave in self.synced:
                lines.append(f"{who} runs on distributed clocks: SYNC0 every period{sync0}"
                             + (" (the reference clock)" if joint.slave == self.reference else ""))
            else:
                lines.append(f"{who} runs free on the frames, without distributed clocks: {self.free[joint.slave]}")
        return lines + ([self.slide] if self.slide else [])


def dc_plan(joints: Sequence[JointConfig], assign_activate: Sequence[int], dc_units: Sequence[bool]) -> \
        tuple[DcPlan, str]:
    """Each joint's way to run from its ``dc`` setting, its ESI, its slave's SII (``assign_activate``:
    the SII's DC mode, 0 none) and its ESC (``dc_units``: feature register 0x0008 bit 2, as SOEM
    reads it: the reference clock is the first slave with a DC unit, and every slave with one takes
    part in the FRMW); with the first problem ('' none): ``dc = true`` on a slave without DC."""
    plan = DcPlan()
    for joint, assign, unit in zip(joints, assign_activate, dc_units, strict=True):
        if unit:
            plan.with_dc += 1
            plan.reference = plan.reference or joint.slave
        if joint.dc is False:
            plan.free[joint.slave] = "dc = false in the app file"
        elif not unit or not assign:
            why = ("has no DC unit (ESC feature register 0x0008)" if not unit else
                   "describes no DC mode in its SII (category 60)")
            if joint.dc:
                return plan, f"joints[{joint.slave - 1}].dc: slave {joint.slave} {why}: it cannot run on them"
            plan.free[joint.slave] = f"the slave {why}"
        elif joint.esi_dc is False:
            plan.free[joint.slave] = "its ESI file describes no DC mode"
        else:
            plan.synced[joint.slave] = assign
    return plan, ""


def first_release(t0_ns: int, period_ns: int, now_ns: int, lead_ns: int = SYNC0_LEAD_NS) -> int:
    """The first k ≥ 0 whose release T0 + kP is at least ``lead_ns`` after ``now_ns``."""
    wait_ns = now_ns + lead_ns - t0_ns
    return max(0, -(-wait_ns // period_ns))


def _transact(sock: socket.socket, command: int, address: int, data: bytes, timeout_s: float = 0.05) -> \
        tuple[int, bytes]:
    """One datagram out and its answer back: (working counter, data); (-1, b'') when none came."""
    frame = new_frame(12 + len(data))
    put_datagram(frame, 16, command, DC_INDEX, address, len(data))
    frame[DATA_AT:DATA_AT + len(data)] = data
    sock.send(frame)
    deadline = time.monotonic() + timeout_s
    reply = bytearray(len(frame) + 64)
    while time.monotonic() < deadline:
        try:
            size = sock.recv_into(reply)
        except (TimeoutError, BlockingIOError):
            continue
        if size >= DATA_AT + len(data) + 2 and reply[16] == command and reply[17] == DC_INDEX:
            wkc_at = DATA_AT + len(data)
            return reply[wkc_at] | reply[wkc_at + 1] << 8, bytes(reply[DATA_AT:wkc_at])
    return -1, b""


def read_system_time(sock: socket.socket, position: int) -> tuple[int, int, int]:
    """The slave's DC system time, the CLOCK_MONOTONIC instant it stands for (the midpoint of the
    exchange) and the exchange's round trip (twice the mapping's uncertainty), in ns; raises
    OSError when the slave does not answer."""
    before = time.monotonic_ns()
    wkc, data = _transact(sock, FPRD, station(position) | REG_SYSTEM_TIME << 16, bytes(8))
    after = time.monotonic_ns()
    if wkc != 1:
        raise OSError(f"slave {position} did not answer the read of its system time (0x0910)")
    return struct.unpack("<Q", data)[0], (before + after) // 2, after - before


def start_sync0(sock: socket.socket, position: int, start_ns: int, cycle_ns: int, assign_activate: int) -> None:
    """SYNC0 of the slave at ``position``: deactivated, start time (system time) and cycle time set,
    then activated with its AssignActivate, as a master does; raises OSError when a write is not taken."""
    address = station(position)
    for register, data in ((REG_CYCLIC_CONTROL, struct.pack("<H", 0)),
                           (REG_SYNC0_START, struct.pack("<Q", start_ns)),
                           (REG_SYNC0_CYCLE, struct.pack("<I", cycle_ns)),
                           (REG_CYCLIC_CONTROL, struct.pack("<H", assign_activate))):
        wkc, _ = _transact(sock, FPWR, address | register << 16, data)
        if wkc != 1:
            raise OSError(f"slave {position} did not take the write of register 0x{register:04X} "
                          f"(working counter {wkc})")


def has_dc_unit(slave: Any, assign_activate: int) -> bool:
    """Whether a pysoem slave's ESC has a DC unit (feature register 0x0008, bit 2: what SOEM goes
    by); where pysoem cannot read the register, whether its SII describes a DC mode."""
    try:
        features = bytes(slave._fprd(0x0008, 2))  # pysoem's FPRD primitive
    except Exception:  # (an older pysoem without it, or no answer: the SII says it)
        return bool(assign_activate)
    return len(features) == 2 and bool(features[0] & 0x04)


def start_on_release(sock: socket.socket, plan: DcPlan, t0_ns: int, period_ns: int, shift_ns: int = 0) -> None:
    """SYNC0 of every slave ``plan`` syncs, on the first release T0 + kP at least ``SYNC0_LEAD_NS``
    ahead (``shift_ns`` after it), mapped into the DC system time through the reference clock's
    time read now, its cycle time the period; the mapping and what it did kept in ``plan``.
    OSError: a slave did not answer or take a write; ValueError: a period SYNC0's cycle register
    cannot hold."""
    if period_ns > MAX_SYNC0_CYCLE_NS:
        raise ValueError(f"a period of {period_ns} ns does not fit SYNC0's cycle time register (32 bits, at "
                         "most 4.29 s): run these drives without distributed clocks (dc = false)")
    try:
        system_ns, monotonic_ns, round_trip_ns = read_system_time(sock, plan.reference)
        offset_ns = system_ns - monotonic_ns
        k = first_release(t0_ns + shift_ns, period_ns, time.monotonic_ns())
        start_ns = t0_ns + k * period_ns + shift_ns + offset_ns
        for position, assign in plan.synced.items():
            start_sync0(sock, position, start_ns, period_ns, assign)
    except OSError as error:
        raise OSError(f"{error} (the reference clock is slave {plan.reference})") from None
    plan.offset_ns, plan.mapped_at_ns, plan.uncertainty_ns = offset_ns, monotonic_ns, round_trip_ns // 2
    shift = f" + {shift_ns} ns shift" if shift_ns else ""
    plan.sync0 = (f" from release {k} (T0 + {k}·P{shift} = system time {start_ns} ns; DC system time = "
                  f"CLOCK_MONOTONIC + {offset_ns} ns ± {round_trip_ns // 2} ns, read from the reference clock, "
                  f"slave {plan.reference})")


def measure_slide(sock: socket.socket, plan: DcPlan) -> None:
    """At the end of the run: the reference clock's time read again against CLOCK_MONOTONIC, and
    how far it moved from the mapping SYNC0 started on (rtloop does not correct it: SYNC0 slid that
    far against the releases), into ``plan.slide``."""
    if not plan.mapped_at_ns:
        return
    try:
        system_ns, monotonic_ns, round_trip_ns = read_system_time(sock, plan.reference)
    except OSError as error:
        plan.slide = f"the reference clock's drift was not measured at the end: {error}"
        return
    slide_ns = system_ns - (monotonic_ns + plan.offset_ns)
    elapsed_ns = max(1, monotonic_ns - plan.mapped_at_ns)
    uncertainty_ns = plan.uncertainty_ns + round_trip_ns // 2
    plan.slide = (f"SYNC0 slid {slide_ns / 1000:+.1f} µs ± {uncertainty_ns / 1000:.1f} µs against rtloop's releases "
                  f"over {elapsed_ns / 1e9:.1f} s (the reference clock {slide_ns / elapsed_ns * 1e6:+.1f} ± "
                  f"{uncertainty_ns / elapsed_ns * 1e6:.1f} ppm off CLOCK_MONOTONIC; not corrected)")
