"""Where a servo bus's packets go: a serial line, or a bus model in the same process (the twin)."""

from __future__ import annotations

import errno
import os
import select
import termios
from typing import Any


class PortLine:
    """A serial line's file descriptor: ``os.write`` out, ``poll`` + ``os.readv`` in (nothing kept per call)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.poller = select.poll()
        self.poller.register(fd, select.POLLIN)

    def send(self, data: Any) -> None:
        if os.write(self.fd, data) != len(data):  # (the port is non-blocking: a full output buffer cuts a packet)
            raise OSError(errno.EAGAIN, "the line's output buffer is full: a packet went out cut short")

    def receive(self, buffer: memoryview, timeout_ns: int) -> int:
        if not self.poller.poll(max(0, -(-timeout_ns // 1_000_000))):  # past the deadline: what is there
            return 0
        came = os.readv(self.fd, (buffer,))
        if came == 0:
            raise EOFError("end of file")
        return came

    def flush_input(self) -> None:
        termios.tcflush(self.fd, termios.TCIFLUSH)


class ModelLine:
    """A bus model answering in process: what it answers waits in ``pending`` until received."""

    def __init__(self, bus: Any) -> None:
        self.bus = bus
        self.pending = bytearray()

    def send(self, data: Any) -> None:
        self.pending += self.bus.receive(data)

    def receive(self, buffer: memoryview, timeout_ns: int) -> int:
        """What the model answered (it answers at once: no clock is consulted)."""
        count = min(len(buffer), len(self.pending))
        buffer[:count] = self.pending[:count]
        del self.pending[:count]
        return count

    def flush_input(self) -> None:
        self.pending.clear()
