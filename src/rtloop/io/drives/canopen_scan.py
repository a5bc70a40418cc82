"""CANopen nodes on a CAN interface, for ``rtloop io list --canopen IF``.

An SDO upload of the identity's vendor (0x1018:1) goes to every node id 1..127 at once; each node
that answers within ``wait_s`` is asked for its product and revision, and listed with the NMT state
its last heartbeat said (if it sent one meanwhile). Only SDO uploads are sent: nothing is written
and no node changes state, so a bus that a running task drives can be listed too. What stops a scan
(no CAN in this kernel, no such interface, the interface down, nothing answering) is one entry with
its fix.
"""

from __future__ import annotations

import errno
import socket
import time
from typing import Any

from rtloop.io.drives import canopen_wire as wire
from rtloop.io.inventory import Interface

__all__ = ["canopen_nodes", "scan_nodes"]

NODE_IDS = range(1, 128)


def canopen_nodes(interface: str, wait_s: float = 0.3) -> list[Interface]:
    from rtloop.io.cansocket import CanInterfaceError, can_supported, check_interface

    unsupported = can_supported()
    if unsupported:
        return [Interface("canopen", interface, unsupported, False, "a kernel with SocketCAN (can, vcan modules)")]
    try:
        check_interface(interface, False, "--canopen")
    except CanInterfaceError as error:
        problem = str(error).partition(": ")[2]
        fix = f"sudo ip link set {interface} up type can bitrate 500000" if "down" in problem else \
            "ip -details link show (the CAN port the drives hang on)"
        return [Interface("canopen", interface, problem, False, fix)]
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        sock.bind((interface,))
    except OSError as error:
        return [Interface("canopen", interface, f"cannot open it: {error.strerror}", False, "")]
    try:
        found = scan_nodes(sock, wait_s)
    finally:
        sock.close()
    if not found:
        return [Interface("canopen", interface, f"no CANopen node answered an SDO within {wait_s * 1e3:g} ms", False,
                          "power the drives, check the bit rate and termination (emulated: rtloop io emulate canopen)")]
    return [Interface("canopen", f"{interface} node {node}", describe, True) for node, describe in found]


def _send(sock: Any, frame: bytearray) -> None:
    """Send, waiting while the interface's queue is full (a real bus at 125 kbit/s takes 127 requests
    in about 100 ms; its queue holds 10)."""
    deadline = time.monotonic() + 1.0
    while True:
        try:
            sock.send(frame)
            return
        except OSError as error:
            if error.errno != errno.ENOBUFS or time.monotonic() > deadline:
                raise
            time.sleep(0.001)


def scan_nodes(sock: Any, wait_s: float) -> list[tuple[int, str]]:
    """(node id, what it is) for each node that answers on ``sock`` (a bound CAN_RAW socket, or a
    stand-in with send, recv and settimeout), in node order."""
    for node in NODE_IDS:
        _send(sock, wire.wire_frame(wire.sdo_request_id(node), wire.sdo_upload(0x1018, 1)))
    identity: dict[int, dict[int, int]] = {}
    states: dict[int, int] = {}
    asked: set[tuple[int, int]] = set()
    deadline = time.monotonic() + wait_s
    while (left := deadline - time.monotonic()) > 0:
        sock.settimeout(left)
        try:
            can_id, length, data = wire.WIRE.unpack(sock.recv(16))
        except (TimeoutError, OSError):
            break
        can_id &= 0x1FFFFFFF
        node = can_id & 0x7F
        if can_id - node == 0x700 and node and length >= 1:
            states[node] = data[0] or 0x7F  # a boot-up message: the node is pre-operational now
        elif can_id - node == 0x580 and node and length == 8 and data[1:3] == b"\x18\x10":
            sub = data[3]
            try:
                value = wire.sdo_answer(data, 0x1018, sub)
            except wire.SdoAbort:
                value = None  # a node without the object still answered: it is there
            identity.setdefault(node, {})[sub] = -1 if value is None else int(value)
            for more in (2, 3):  # the rest of the identity, once the node is known to be there
                if (node, more) not in asked:
                    asked.add((node, more))
                    _send(sock, wire.wire_frame(wire.sdo_request_id(node), wire.sdo_upload(0x1018, more)))
            if len(identity[node]) < 3:
                deadline = max(deadline, time.monotonic() + min(wait_s, 0.1))  # its other answers are coming
    found = []
    for node in sorted(identity):
        parts = [f"{name} 0x{identity[node][sub]:08X}" for sub, name in ((1, "vendor"), (2, "product"),
                                                                        (3, "revision"))
                 if identity[node].get(sub, -1) >= 0]
        state = wire.HEARTBEAT_STATES.get(states[node], hex(states[node])) if node in states else \
            "no heartbeat seen"
        found.append((node, f"CANopen node: {', '.join(parts) or 'no identity (0x1018)'}, {state}"))
    return found
