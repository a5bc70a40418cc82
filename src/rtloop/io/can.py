"""CAN devices: the frames an app file declares, sent and received on a SocketCAN interface.

    [devices.drive]
    kind = "can"
    interface = "can0"                       # or vcan0 (virtual, for tests)
    heartbeat = { id = 0x700 }               # one byte counting up every cycle
    send = [{ id = 0x200, signals = [{ name = "torque", start_byte = 0, type = "i16", scale = 0.01 }] }]
    receive = [{ id = 0x180, timeout_ms = 2, on_missing = "fault",
                 signals = [{ name = "position", start_byte = 0, type = "i32", scale = 1e-4 }] }]

The device's ``u`` is every signal of ``send`` in order; its ``y`` every signal of ``receive``.
Each cycle ``write`` sends every declared frame and the heartbeat; ``read`` takes the newest
copy of each received frame, waiting at most its ``timeout_ms`` (counted from the start of
the read) for one that has not come this cycle. A frame still missing then is a fault
(``on_missing = "fault"``) or keeps its last values and counts a stale read (``"stale"``).
Where ``io/_devio.c`` was built (``io/compiled.py``) ``write`` and ``read`` are one C call each
(``CanCycle``); the Python below stays the reference, and says what went wrong in either path.

The heartbeat lets a drive stop by itself: when rtloop stops sending it — the task ends,
is killed, the machine hangs — the drive's own watchdog (CANopen heartbeat consumer, ODrive
``watchdog_timeout``, moteus ``timeout_mode``) sees the counter stop and goes to its safe state.
"""

from __future__ import annotations

import errno
import os
import time
from typing import Any, ClassVar

from rtloop.errors import DeviceError, DeviceFault
from rtloop.io.bytelayout import FloatView, LayoutError
from rtloop.io.canframes import DATA_AT, CanFrame, HeartbeatCounter, check_ids, frame_from_table, heartbeat_from_table
from rtloop.io.compiled import devio
from rtloop.io.device import Claim, Device, FloatVector, Setting

__all__ = ["CanDevice"]


def _list_of_tables(value: list[Any]) -> str | None:
    if not all(isinstance(item, dict) for item in value):
        return "expected an array of tables ({ id = ..., signals = [...] })"
    return None


class CanDevice(Device):
    """Declared CAN frames on one SocketCAN interface (raw ``AF_CAN`` socket)."""

    kind: ClassVar[str] = "can"
    settings: ClassVar[dict[str, Setting]] = {
        "interface": Setting(str, doc="the SocketCAN interface (can0, vcan0)"),
        "fd": Setting(bool, False, "CAN FD frames (up to 64 bytes) on this bus"),
        "send": Setting(list, [], "frames sent every cycle: [{ id, signals = [...] }]", _list_of_tables),
        "receive": Setting(list, [], "frames read every cycle: [{ id, timeout_ms, on_missing, signals }]",
                           _list_of_tables),
        "heartbeat": Setting(dict, {}, "a frame sent every cycle so a drive can go safe by itself: { id = ... }"),
    }

    def __init__(self, name: str, **settings: Any) -> None:
        super().__init__(name, **settings)
        self.interface: str = settings["interface"]
        self.fd: bool = settings["fd"]
        try:
            self.sent = tuple(frame_from_table(table, f"send[{i}]", self.fd, receive=False)
                              for i, table in enumerate(settings["send"]))
            self.received = tuple(frame_from_table(table, f"receive[{i}]", self.fd, receive=True)
                                  for i, table in enumerate(settings["receive"]))
            beat = settings["heartbeat"]
            self.heartbeat_frame = heartbeat_from_table(beat, "heartbeat") if beat else None
            check_ids([*self.sent, *self.received], self.heartbeat_frame)
        except LayoutError as error:
            key, _, problem = str(error).partition(": ")
            raise DeviceError(name, "", key, problem) from None
        self.input_names = tuple(n for frame in self.sent for n in frame.layout.names)
        self.output_names = tuple(n for frame in self.received for n in frame.layout.names)
        self.n_inputs, self.n_outputs = len(self.input_names), len(self.output_names)
        self.socket: Any = None
        self._cycle: Any = None  # the cycle in C (io/_devio.c CanCycle), once attached
        self.active = False
        self.stale_reads = 0
        self.stale_by_frame = [0] * len(self.received)
        self.link_failure = ""  # why the bus refused a send or receive, once it has
        self._u, self._y = FloatView(), FloatView()

    def __getstate__(self) -> dict[str, Any]:
        # travels to the task process unopened
        return {**self.__dict__, "socket": None, "_cycle": None, "active": False}

    # --- supervisor ---------------------------------------------------------------------------
    def check(self) -> None:
        from rtloop.io.cansocket import CanInterfaceError, can_supported, check_interface

        unsupported = can_supported()
        if unsupported:
            raise DeviceError(self.name, "", "interface", f"{self.interface!r}: {unsupported}")
        try:
            check_interface(self.interface, self.fd, "interface")
        except CanInterfaceError as error:
            raise DeviceError(self.name, "", "interface", str(error).partition(": ")[2]) from None

    def claims(self) -> tuple[Claim, ...]:
        """Every id this device sends (heartbeat included) or receives on its interface: a second
        sender of one id on one bus would interleave its commands with ours, and a device receiving
        an id we send would read our commands as its readings (SocketCAN loops a frame back to the
        host's other sockets). Receiving one id in two devices is fine."""
        sent = [*self.sent, *([self.heartbeat_frame] if self.heartbeat_frame else [])]
        return tuple(Claim(("can", self.interface, frame.wire_id), f"{frame.where}.id",
                           f"frame id clash: 0x{frame.can_id:X} on {self.interface} is also",
                           "received" if receive else "sent", shared=receive)
                     for frames, receive in ((sent, False), (self.received, True)) for frame in frames)

    # --- task process ---------------------------------------------------------------------------
    def configure(self) -> None:
        from rtloop.io.cansocket import CanInterfaceError, CanSocket

        try:
            self.attach(CanSocket(self.interface, self.fd, self.received, f"devices.{self.name}"))
        except CanInterfaceError as error:
            raise DeviceError(self.name, "", "interface", str(error).partition(": ")[2]) from None

    def attach(self, sock: Any) -> None:
        """Use the open :class:`~rtloop.io.cansocket.CanSocket` ``sock`` and build the per-cycle plans."""
        self.socket = sock
        # Wire frames built once; write() only rewrites their data bytes.
        self._sent_buffers = [frame.new_buffer() for frame in self.sent]
        self._heartbeat = HeartbeatCounter(self.heartbeat_frame) if self.heartbeat_frame else None
        self._plan_read = [(frame, latest, first) for frame, latest, first in
                           zip(self.received, self.socket.latest, _starts(self.received), strict=True)]
        self._plan_write = [(frame.layout.pack_into, buffer, first) for frame, buffer, first in
                            zip(self.sent, self._sent_buffers, _starts(self.sent), strict=True)]
        self._send = sock.sock.send
        self._cycle = self._compiled_cycle(sock)

    def _compiled_cycle(self, sock: Any) -> Any:
        """The whole cycle in C (io/_devio.c CanCycle) where it was built, on this socket's frames;
        None where the Python reference runs (``RTLOOP_PURE_PYTHON=1``, no compiler)."""
        compiled, receiver = devio(), getattr(sock, "_receiver", None)
        layouts = [frame.layout._compiled for frame in (*self.sent, *self.received)]
        if compiled is None or receiver is None or any(layout is None for layout in layouts):
            return None
        return compiled.CanCycle(receiver, self._sent_buffers, layouts[:len(self.sent)],
                                 self._heartbeat.buffer if self._heartbeat is not None else None,
                                 layouts[len(self.sent):], [frame.timeout_ns for frame in self.received],
                                 [frame.on_missing == "fault" for frame in self.received])

    def activate(self) -> None:
        """At T0: drop what came before it (frames of an earlier run); from now on frames go out."""
        try:
            self.socket._drain()
        except OSError as error:
            raise self.link_failed(error, "receiving") from None
        self.active = True

    def link_failed(self, error: OSError, doing: str) -> DeviceFault:
        """A send or receive the bus refused: the interface went down, the controller went bus-off, the
        adapter was unplugged. A field event, as a serial line that hangs up: one line naming the device
        and the interface (the task stops; its safe values are tried on the way out)."""
        reason = os.strerror(error.errno) if error.errno else str(error)
        self.link_failure = f"{reason}{LINK_HINTS.get(error.errno or 0, '')}"
        heartbeat = ", and its heartbeat stops (a drive watching it goes safe by itself)" \
            if self.heartbeat_frame else ""
        return DeviceFault(f"device {self.name!r}: {doing} on CAN interface {self.interface} failed: "
                           f"{self.link_failure}; its safe values are tried{heartbeat}")

    # --- the cycle: one C call each where built, else the Python reference -----------------------
    def write(self, u: FloatVector) -> None:
        cycle = self._cycle
        if cycle is not None:
            try:
                bad = cycle.write(u)
            except TypeError:  # not a float64 vector of u's length: the reference, its heartbeat counting on
                self._write_reference_with(cycle, u)
                return
            except OSError as error:
                raise self.link_failed(error, "sending") from None
            if bad >= 0:  # the frames before it went out; the reference names the value that cannot be sent
                pack_into, buffer, first = self._plan_write[bad]
                pack_into(buffer, DATA_AT, self._u.of(u), first)  # raises its ValueError
            return
        self._write_reference(u)

    def _write_reference_with(self, cycle: Any, u: FloatVector) -> None:
        heartbeat = self._heartbeat
        if heartbeat is None:
            self._write_reference(u)
            return
        heartbeat.count = cycle.count
        try:
            self._write_reference(u)
        finally:
            cycle.count = heartbeat.count

    def _write_reference(self, u: FloatVector) -> None:
        send, u = self._send, self._u.of(u)
        try:
            for pack_into, buffer, first in self._plan_write:
                pack_into(buffer, DATA_AT, u, first)
                send(buffer)
            if self._heartbeat is not None:
                send(self._heartbeat.next())
        except OSError as error:
            raise self.link_failed(error, "sending") from None

    def read(self, y: FloatVector) -> None:
        cycle = self._cycle
        if cycle is not None:
            try:
                if cycle.read(y):
                    return  # every frame came, all in y
            except TypeError:  # not a float64 vector of y's length: the reference
                self._read_reference(y)
                return
            except OSError as error:
                raise self.link_failed(error, "receiving") from None
            # C unpacked what came up to the first missing frame that faults: count and raise as the reference
            for index, frame in enumerate(self.received):
                if not self.socket.fresh[index]:
                    self._missed(index, frame)
            return
        self._read_reference(y)

    def _missed(self, index: int, frame: CanFrame) -> None:
        if frame.on_missing == "stale":
            self.stale_reads += 1  # y keeps the values of the last frame that came
            self.stale_by_frame[index] += 1
        else:
            raise DeviceFault(_missing(self.name, frame))

    def _read_reference(self, y: FloatVector) -> None:
        sock, y = self.socket, self._y.of(y)
        try:
            sock.receive_cycle(time.monotonic_ns())
        except OSError as error:
            raise self.link_failed(error, "receiving") from None
        fresh = sock.fresh
        for index, (frame, latest, first) in enumerate(self._plan_read):
            if fresh[index]:
                frame.layout.unpack_from(latest, DATA_AT, y, first)
            else:
                self._missed(index, frame)

    def may_read_stale(self) -> bool:
        return any(frame.on_missing == "stale" for frame in self.received)

    def stale_sources(self) -> dict[str, int]:
        return {f"{frame.where} (id 0x{frame.can_id:X})": count
                for frame, count in zip(self.received, self.stale_by_frame, strict=True) if count}

    def write_safe(self, u: FloatVector) -> None:
        """The safe values, in the declared frames, with the heartbeat — once active only.

        Before T0 nothing goes out: a drive answers every command frame, and an answer that
        arrives after ``activate`` has dropped what came would be taken for the first cycle's
        reading (and every reading after it one cycle late: the run would leave its simulation
        with no deadline missed). A drive that has heard no heartbeat yet is disabled by its own
        watchdog: that is its safe state until the first cycle."""
        if self.socket is not None and self.active:
            try:
                self.write(u)
            except DeviceFault:  # what became of the safe values, in the run's notes
                raise DeviceFault(f"device {self.name!r}: its safe values could not be sent on CAN interface "
                                  f"{self.interface}: {self.link_failure}") from None

    def write_safe_for_dead_task(self, u: FloatVector) -> str:
        """From the supervisor: the declared frames with the safe values, once, on a socket of its
        own — and no heartbeat, so a drive that watches it still sees the loop is gone."""
        from rtloop.io.cansocket import CanSocket

        if not self.sent:
            return ""
        sock = CanSocket(self.interface, self.fd, (), f"devices.{self.name}")
        try:
            for frame, first in zip(self.sent, _starts(self.sent), strict=True):
                buffer = frame.new_buffer()
                frame.layout.pack_into(buffer, DATA_AT, u, first)
                sock.send(buffer)
        finally:
            sock.close()
        ids = ", ".join(f"0x{frame.can_id:X}" for frame in self.sent)
        return f"sent its frames {ids} with the safe values on {self.interface} (no heartbeat)"

    def close(self) -> None:
        self.active = False
        if self._cycle is not None:
            self._cycle.release()  # before the socket it sends on is closed (and its number reused)
            self._cycle = None
        if self.socket is not None:
            self.socket.close()
            self.socket = None


LINK_HINTS = {
    errno.ENETDOWN: " (the interface is down: a controller gone bus-off without restart-ms, or set down)",
    errno.ENODEV: " (the interface is gone: a USB adapter unplugged?)",
    errno.ENOBUFS: " (the transmit queue is full: no node acknowledges, or the controller is bus-off)",
    errno.EAGAIN: " (the transmit queue is full: no node acknowledges, or the controller is bus-off)",
}
"""What a failed send or receive most likely means on the bus, by errno."""


def _starts(frames: tuple[CanFrame, ...]) -> list[int]:
    """Where each frame's signals start in the device's ``u`` (or ``y``)."""
    starts, at = [], 0
    for frame in frames:
        starts.append(at)
        at += len(frame.layout)
    return starts


def _missing(device: str, frame: CanFrame) -> str:
    return (f"devices.{device}.{frame.where} (id 0x{frame.can_id:X}): no frame within "
            f"{frame.timeout_ns / 1e6:g} ms (on_missing = \"fault\")")
