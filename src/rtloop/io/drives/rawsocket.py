"""Raw EtherCAT frames on a Linux network interface (``AF_PACKET``, EtherType 0x88A4).

Used by the EtherCAT drive device for its one frame per cycle, by the emulated slaves for their
answers, and by the benchmark's bare exchange. Needs ``CAP_NET_RAW`` (root).
"""

from __future__ import annotations

import os
import socket
import struct

__all__ = ["ETHERTYPE_ECAT", "FRAME_BYTES", "RAW_SOCKET_PERMISSION", "interface_problem", "open_raw", "put_datagram"]

ETHERTYPE_ECAT = 0x88A4
FRAME_BYTES = 1514
"""The largest Ethernet frame without its check sequence."""
MAX_DATAGRAM_DATA = FRAME_BYTES - 14 - 2 - 12
"""Data one datagram carries when it is the frame's only one."""
_PACKET_IGNORE_OUTGOING = 23  # <linux/if_packet.h>; Linux 4.20+
_SOL_PACKET = 263  # <linux/socket.h>
MASTER_MAC = b"\x02\x00\x00\x00\x00\x01"  # locally administered
BROADCAST_MAC = b"\xff" * 6
RAW_SOCKET_PERMISSION = ("run rtloop as root (a sudo user: sudo \"$(command -v rtloop)\" ..., or tools/as-root in a "
                         "clone); not setcap cap_net_raw on python3, which would give raw sockets to every Python "
                         "program on the machine")
"""What to do when a raw socket is refused (a user's process lacks CAP_NET_RAW)."""


def interface_problem(name: str) -> str | None:
    """Why ``name`` cannot carry EtherCAT frames now (missing, down), with the fix; None when it can."""
    base = f"/sys/class/net/{name}"
    if not name or "/" in name or not os.path.isdir(base):
        try:
            found = ", ".join(sorted(n for n in os.listdir("/sys/class/net") if n != "lo")) or "none"
        except OSError:
            found = "unknown"
        return f"no network interface {name!r} here (interfaces: {found})"
    try:
        with open(f"{base}/flags") as flags_file:
            flags = int(flags_file.read().strip(), 16)
    except (OSError, ValueError):
        return None
    if not flags & 0x1:  # IFF_UP
        return f"interface {name} is down: sudo ip link set {name} up"
    return None


def open_raw(name: str, timeout_s: float | None = None, receive_timeout_us: int | None = None) -> socket.socket:
    """A raw socket on ``name`` for EtherCAT frames only, that does not see its own frames.

    ``timeout_s``: Python's timeout (a poll before each call). ``receive_timeout_us`` instead: the
    socket stays blocking and a receive ends with BlockingIOError after this long (SO_RCVTIMEO,
    which the kernel counts in ticks, rounding up: 1 µs is one tick), one syscall per receive."""
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETHERTYPE_ECAT))
    try:
        sock.bind((name, ETHERTYPE_ECAT))
        try:
            sock.setsockopt(_SOL_PACKET, _PACKET_IGNORE_OUTGOING, 1)
        except OSError:
            pass  # older kernels: the kernel does not loop a socket's own frames back to it anyway
        sock.settimeout(timeout_s)
        if receive_timeout_us is not None:
            timeval = struct.pack("@ll", *divmod(max(1, receive_timeout_us), 1_000_000))
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, timeval)
    except BaseException:
        sock.close()
        raise
    return sock


def put_datagram(frame: bytearray, at: int, command: int, index: int, address: int, length: int,
                 more: bool = False) -> int:
    """Write a datagram header at ``at`` (its data zeroed, working counter 0); returns where the
    next datagram starts."""
    struct.pack_into("<BBIHH", frame, at, command, index, address, length | (0x8000 if more else 0), 0)
    frame[at + 10:at + 10 + length] = bytes(length)
    struct.pack_into("<H", frame, at + 10 + length, 0)
    return at + 12 + length


def new_frame(datagram_bytes: int) -> bytearray:
    """An Ethernet + EtherCAT header for ``datagram_bytes`` of datagrams (padded to Ethernet's 60)."""
    size = max(60, 14 + 2 + datagram_bytes)
    frame = bytearray(size)
    frame[0:6] = BROADCAST_MAC
    frame[6:12] = MASTER_MAC
    struct.pack_into(">H", frame, 12, ETHERTYPE_ECAT)
    struct.pack_into("<H", frame, 14, datagram_bytes | 0x1000)  # type 1: EtherCAT commands
    return frame
