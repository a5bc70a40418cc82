"""A raw SocketCAN socket (``AF_CAN``/``CAN_RAW``) with buffers allocated once.

Only the declared receive ids pass the kernel's filter, so a busy bus costs this task
nothing for frames it does not use. Sending is one ``send`` of a prebuilt frame; receiving
drains the socket without blocking and waits (``ppoll``, to the nanosecond) only while a frame
it expects this cycle has not come. python-can's SocketCAN bus does the same work with an object per frame
(tens of µs a frame by its own figures): too much for a 1 kHz loop, so it is used here only
as the benchmark's reference.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import select
import socket
import struct
import time
from collections.abc import Sequence
from pathlib import Path

from rtloop.errors import AppError
from rtloop.io.canframes import CAN_EFF_FLAG, CAN_EFF_MASK, CAN_SFF_MASK, FD_MTU, CanFrame
from rtloop.io.compiled import devio

ARPHRD_CAN = 280  # /sys/class/net/IF/type of a CAN interface
CAN_RAW_FILTER = getattr(socket, "CAN_RAW_FILTER", 1)
CAN_RAW_FD_FRAMES = getattr(socket, "CAN_RAW_FD_FRAMES", 5)
SOL_CAN_RAW = getattr(socket, "SOL_CAN_RAW", 101)
CAN_FILTER = struct.Struct("=II")  # struct can_filter { canid_t can_id; canid_t can_mask; }
CAN_ID = struct.Struct("=I")
NS_PER_S = 1_000_000_000


class _PollFd(ctypes.Structure):
    _fields_ = [("fd", ctypes.c_int), ("events", ctypes.c_short), ("revents", ctypes.c_short)]


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


_libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
_libc.ppoll.argtypes = [ctypes.c_void_p, ctypes.c_ulong, ctypes.c_void_p, ctypes.c_void_p]
_libc.ppoll.restype = ctypes.c_int


class ReadableWait:
    """Wait until one descriptor is readable, for a time in nanoseconds: ``ppoll`` with a timespec
    (select.poll counts whole milliseconds, so a 0.2 ms timeout would wait 1 ms). Its buffers are
    made once; a wait allocates nothing that stays. The C twin calls ppoll itself (io/_devio.c)."""

    def __init__(self, fd: int) -> None:
        self._pollfd = _PollFd(fd, select.POLLIN, 0)
        self._timeout = _Timespec()
        self._pollfd_ref, self._timeout_ref = ctypes.byref(self._pollfd), ctypes.byref(self._timeout)

    def wait(self, wait_ns: int) -> bool:
        """True when readable (or a signal came: the caller works its wait out again), False after ``wait_ns``."""
        self._timeout.tv_sec, self._timeout.tv_nsec = divmod(wait_ns, NS_PER_S)
        ready: int = _libc.ppoll(self._pollfd_ref, 1, self._timeout_ref, None)
        if ready < 0:
            error = ctypes.get_errno()
            if error == errno.EINTR:  # the handler runs as this returns; the wait is worked out again
                return True
            raise OSError(error, os.strerror(error))  # as the C twin's PyErr_SetFromErrno
        return ready > 0


class CanInterfaceError(AppError):
    """The declared CAN interface cannot be used (missing, not CAN, down, no FD)."""


def check_interface(name: str, fd: bool, where: str) -> None:
    """Refuse, in one line, an interface that is missing, not CAN, down, or too small for FD frames."""
    if not name or "/" in name or name in (".", ".."):
        raise CanInterfaceError(f"{where}: {name!r} is not a network interface name")
    folder = Path("/sys/class/net") / name
    if not folder.exists():
        present = sorted(p.name for p in Path("/sys/class/net").iterdir()
                         if _read(p / "type") == str(ARPHRD_CAN)) if Path("/sys/class/net").exists() else []
        found = f"CAN interfaces here: {', '.join(present)}" if present else "this machine has no CAN interface"
        raise CanInterfaceError(f"{where}: no network interface {name!r} ({found})")
    if _read(folder / "type") != str(ARPHRD_CAN):
        raise CanInterfaceError(f"{where}: {name!r} is not a CAN interface")
    flags = int(_read(folder / "flags") or "0", 16)
    if not flags & 0x1:  # IFF_UP
        raise CanInterfaceError(f"{where}: CAN interface {name!r} is down (ip link set {name} up, after setting "
                                "its bitrate)")
    if fd and int(_read(folder / "mtu") or "0") < FD_MTU:
        raise CanInterfaceError(f"{where}: {name!r} does not carry CAN FD frames (its MTU is not {FD_MTU}: "
                                f"ip link set {name} mtu {FD_MTU}, or 'fd on' for a controller)")


def _read(path: Path) -> str:
    try:
        return path.read_text().strip()
    except OSError:
        return ""


class CanSocket:
    """One raw CAN socket on one interface, for the declared frames of one device."""

    def __init__(self, interface: str, fd: bool, receive: Sequence[CanFrame], where: str,
                 sock: socket.socket | None = None) -> None:
        """``sock``: an already open datagram socket to use instead (the benchmark's stand-in where
        the kernel has no CAN: same send, poll and recv_into calls, on a UNIX socket pair)."""
        self.interface = interface
        self.where = where
        self.receive = tuple(receive)
        self.sock = sock if sock is not None else self._open(interface, fd, where)
        self.sock.setblocking(False)
        self.fileno = self.sock.fileno()
        self.poller = select.poll()
        self.poller.register(self.fileno, select.POLLIN)
        self.readable = ReadableWait(self.fileno)
        self.incoming = bytearray(FD_MTU)
        self.incoming_view = memoryview(self.incoming)
        self.index_of = {frame.wire_id: index for index, frame in enumerate(self.receive)}
        self.latest = [bytearray(frame.mtu) for frame in self.receive]
        self.fresh = [False] * len(self.receive)
        self.none_fresh = [False] * len(self.receive)
        self._unexpected = 0
        compiled = devio()  # the drain in C (io/_devio.c), where it was built
        self._receiver = compiled.CanReceiver(self.fileno, [frame.wire_id for frame in self.receive], self.latest,
                                              self.fresh) if compiled else None
        if self._receiver is not None:
            self._drain = self._receiver.drain  # type: ignore[method-assign]  # the C drain, in this instance's place

    @property
    def unexpected(self) -> int:
        """Frames that passed the filter but are not a declared frame's size (an FD frame where a
        classic one was declared, or the stand-in socket's strays): counted, never decoded."""
        return self._receiver.unexpected if self._receiver is not None else self._unexpected

    def _open(self, interface: str, fd: bool, where: str) -> socket.socket:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        try:
            if fd:
                sock.setsockopt(SOL_CAN_RAW, CAN_RAW_FD_FRAMES, 1)
            filters = b"".join(CAN_FILTER.pack(frame.wire_id, (CAN_EFF_FLAG | CAN_EFF_MASK) if frame.extended
                                               else (CAN_EFF_FLAG | CAN_SFF_MASK)) for frame in self.receive)
            # no receive frame declared: an empty filter list receives nothing
            sock.setsockopt(SOL_CAN_RAW, CAN_RAW_FILTER, filters)
            sock.bind((interface,))
        except OSError as error:
            sock.close()
            raise CanInterfaceError(f"{where}: cannot open CAN interface {interface!r}: {error.strerror}") from None
        return sock

    def send(self, frame: bytearray) -> None:
        """Send one prebuilt wire frame (a full transmit queue is an error, not a wait)."""
        try:
            self.sock.send(frame)
        except OSError as error:
            raise self.send_failed(error) from None

    def send_failed(self, error: OSError) -> OSError:
        """What a failed send means, in one line naming the device and the interface."""
        hint = (" (the transmit queue is full: no node acknowledges, or the controller is bus-off)"
                if error.errno in (errno.ENOBUFS, errno.EAGAIN) else "")
        return OSError(error.errno, f"{self.where}: sending on {self.interface}: {error.strerror}{hint}")

    def _drain(self) -> int:
        """Take every frame already queued, keeping the newest of each id; how many expected ones came."""
        sock, incoming, poller, latest, fresh = self.sock, self.incoming, self.poller, self.latest, self.fresh
        came = 0
        while poller.poll(0):
            size = sock.recv_into(incoming)
            index = self.index_of.get(CAN_ID.unpack_from(incoming, 0)[0], -1)
            if index < 0 or size != len(latest[index]):  # not declared, or FD where classic was declared
                self._unexpected += 1
                continue
            latest[index][:] = self.incoming_view[:size]
            if not fresh[index]:
                fresh[index] = True
                came += 1
        return came

    def receive_cycle(self, start_ns: int) -> None:
        """Drain, then wait while an expected frame is still missing and its timeout has not passed.

        After it, ``fresh[i]`` says whether frame i came this cycle and ``latest[i]`` holds its newest copy."""
        fresh = self.fresh
        fresh[:] = self.none_fresh
        missing = len(fresh) - self._drain()
        while missing:
            wait_ns = 0
            now_ns = time.monotonic_ns()
            for index, frame in enumerate(self.receive):
                if not fresh[index] and start_ns + frame.timeout_ns - now_ns > wait_ns:
                    wait_ns = start_ns + frame.timeout_ns - now_ns
            if wait_ns <= 0 or not self.readable.wait(wait_ns):
                return  # what is still missing stays so: the device counts it or faults
            missing -= self._drain()

    def close(self) -> None:
        if self._receiver is not None:
            self._receiver.release()  # before the descriptor it polls is closed (and its number reused)
        self.sock.close()


def can_supported() -> str:
    """"" when this kernel opens AF_CAN sockets, else why not."""
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (OSError, AttributeError) as error:
        return f"this kernel opens no CAN socket ({getattr(error, 'strerror', None) or error})"
    return ""
