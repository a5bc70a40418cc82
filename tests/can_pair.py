"""A CAN device on a UNIX socket pair in its bus's place, for the tests that run anywhere (this
kernel may have no CAN): a SOCK_SEQPACKET pair keeps each frame whole as a CAN_RAW socket does, and
the device makes the same calls on it (send, poll, recv_into). What the test sends on the pair's
other end, the device receives; what the device sends, the test reads there."""

from __future__ import annotations

import socket
import struct
from typing import Any


def attach_to_a_pair(device: Any, fd: bool = False) -> socket.socket:
    """Attach ``device`` (built, not configured) to one end of a new pair; the other end, the test's."""
    from rtloop.io.cansocket import CanSocket

    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    device.attach(CanSocket("pair", fd, device.received, f"devices.{device.name}", sock=ours))
    return peer


def wire_frame(can_id: int, data: bytes, fd: bool = False) -> bytes:
    """A frame as the kernel hands it to a CAN_RAW socket (``struct can_frame``, or ``canfd_frame``)."""
    return struct.pack("=IB3x64s" if fd else "=IB3x8s", can_id, len(data), data)
