"""CAN frames declared in an app file: ids, lengths, the signals in their bytes.

This module is pure (no socket): it checks the declaration once — ids in range and not
used twice, lengths a CAN or CAN FD frame can have, every signal inside its frame — and
turns values into the bytes of a SocketCAN ``struct can_frame`` / ``struct canfd_frame``
and back. ``io/can.py`` moves those bytes through a raw ``AF_CAN`` socket.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from rtloop.io.bytelayout import ByteLayout, LayoutError, field_from_table
from rtloop.io.device import HOUR_MS

CAN_EFF_FLAG = 0x80000000  # the id is a 29-bit (extended) one
CAN_SFF_MASK = 0x7FF
CAN_EFF_MASK = 0x1FFFFFFF
CANFD_BRS = 0x01  # flag: switch to the data bit rate for the payload

CLASSIC_MTU = 16  # sizeof(struct can_frame)
FD_MTU = 72  # sizeof(struct canfd_frame)
# struct can_frame { canid_t can_id; u8 len; u8 pad, res0, len8_dlc; u8 data[8]; } (host byte order)
# struct canfd_frame { canid_t can_id; u8 len; u8 flags, res0, res1; u8 data[64]; }
HEADER = struct.Struct("=IBB2x")
DATA_AT = HEADER.size
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
ON_MISSING = ("fault", "stale")


@dataclass(frozen=True, slots=True)
class CanFrame:
    """One declared frame: its id, its data length and the signals in it."""

    can_id: int
    extended: bool
    fd: bool
    length_bytes: int
    layout: ByteLayout
    where: str
    timeout_ns: int = 0
    """Receive frames: how old the newest copy may be before it counts as missing."""
    on_missing: str = "fault"

    @property
    def wire_id(self) -> int:
        """The id as SocketCAN carries it (29-bit ids with ``CAN_EFF_FLAG``)."""
        return self.can_id | CAN_EFF_FLAG if self.extended else self.can_id

    @property
    def mtu(self) -> int:
        return FD_MTU if self.fd else CLASSIC_MTU

    def new_buffer(self) -> bytearray:
        """A wire frame with this frame's header filled in: allocated once, rewritten every cycle."""
        buffer = bytearray(self.mtu)
        HEADER.pack_into(buffer, 0, self.wire_id, self.length_bytes, CANFD_BRS if self.fd else 0)
        return buffer

    def describe(self) -> str:
        return f"{self.where} (id 0x{self.can_id:X})"


def _integer(table: Mapping[str, Any], key: str, where: str, default: Any = None) -> int:
    value = table.get(key, default)
    if not isinstance(value, int) or isinstance(value, bool):
        raise LayoutError(f"{where}.{key}: expected an integer, got {value!r}")
    return value


def frame_from_table(table: Mapping[str, Any], where: str, fd_bus: bool, receive: bool) -> CanFrame:
    """A :class:`CanFrame` from its app-file table; ``where`` names it in error messages."""
    known = {"id", "extended", "fd", "length", "signals"} | ({"timeout_ms", "on_missing"} if receive else set())
    unknown = sorted(set(table) - known)
    if unknown:
        raise LayoutError(f"{where}: unknown key {unknown[0]!r} (a {'received' if receive else 'sent'} frame has "
                          f"{', '.join(sorted(known))})")
    can_id = _integer(table, "id", where)
    extended = table.get("extended", False)
    if not isinstance(extended, bool):
        raise LayoutError(f"{where}.extended: expected true or false, got {extended!r}")
    largest = CAN_EFF_MASK if extended else CAN_SFF_MASK
    if not 0 <= can_id <= largest:
        shown = f"0x{can_id:X}" if can_id >= 0 else str(can_id)  # not 0x-1
        raise LayoutError(f"{where}.id: {shown} is outside the {'29' if extended else '11'}-bit range "
                          f"0..0x{largest:X}" + ("" if extended else " (set extended = true for 29-bit ids)"))
    fd = table.get("fd", fd_bus)
    if not isinstance(fd, bool):
        raise LayoutError(f"{where}.fd: expected true or false, got {fd!r}")
    if fd and not fd_bus:
        raise LayoutError(f"{where}.fd: a CAN FD frame on a bus not declared fd = true")
    signals = table.get("signals", [])
    if not isinstance(signals, list) or not all(isinstance(s, Mapping) for s in signals):
        raise LayoutError(f"{where}.signals: expected a list of tables ({{name, start_byte, type, scale, offset}})")
    fields = [field_from_table(signal, f"{where}.signals[{i}]") for i, signal in enumerate(signals)]
    needed = max((f.start_byte + f.size_bytes for f in fields), default=0)
    length = table.get("length", needed if fd else 8)
    if not isinstance(length, int) or isinstance(length, bool):
        raise LayoutError(f"{where}.length: expected an integer, got {length!r}")
    if fd and length not in FD_LENGTHS:
        fits = next((n for n in FD_LENGTHS if n >= length), None)
        hint = f" (the next one is {fits})" if fits is not None else ""
        raise LayoutError(f"{where}.length: a CAN FD frame carries one of {', '.join(map(str, FD_LENGTHS))} bytes, "
                          f"not {length}{hint}")
    if not fd and not 0 <= length <= 8:
        raise LayoutError(f"{where}.length: a classic CAN frame carries 0 to 8 bytes, not {length}"
                          + (" (declare the bus fd = true for up to 64)" if length > 8 else ""))
    layout = ByteLayout(fields, length, f"{where}.signals")
    timeout_ns, on_missing = 0, "fault"
    if receive:
        timeout_ms = table.get("timeout_ms")
        if (isinstance(timeout_ms, bool) or not isinstance(timeout_ms, int | float) or not math.isfinite(timeout_ms)
                or timeout_ms <= 0):
            raise LayoutError(f"{where}.timeout_ms: expected a positive number of milliseconds, got {timeout_ms!r}")
        if timeout_ms > HOUR_MS:
            raise LayoutError(f"{where}.timeout_ms: must be at most {HOUR_MS} (an hour), got {timeout_ms!r}")
        timeout_ns = round(timeout_ms * 1_000_000)
        on_missing = table.get("on_missing", "fault")
        if on_missing not in ON_MISSING:
            raise LayoutError(f"{where}.on_missing: expected 'fault' or 'stale', got {on_missing!r}")
    return CanFrame(can_id, extended, fd, length, layout, where, timeout_ns, on_missing)


def check_ids(frames: Sequence[CanFrame], heartbeat: CanFrame | None = None) -> None:
    """Refuse two frames with one id on one bus (a receiver could not tell them apart)."""
    seen: dict[int, CanFrame] = {}
    for frame in [*frames, *([heartbeat] if heartbeat else [])]:
        other = seen.get(frame.wire_id)
        if other is not None:
            raise LayoutError(f"{frame.where}.id: frame id clash: 0x{frame.can_id:X} is also the id of {other.where}")
        seen[frame.wire_id] = frame


def heartbeat_from_table(table: Mapping[str, Any], where: str) -> CanFrame:
    """The heartbeat frame: one byte, a counter that moves every cycle (a drive's watchdog feeds on it)."""
    known = {"id", "extended"}
    unknown = sorted(set(table) - known)
    if unknown:
        raise LayoutError(f"{where}: unknown key {unknown[0]!r} (the heartbeat has id and extended)")
    frame = frame_from_table({**table, "length": 1, "fd": False}, where, fd_bus=True, receive=False)
    return frame


class HeartbeatCounter:
    """The heartbeat's single data byte: 0, 1, ... 255, 0, ... — a stuck value means a stuck sender."""

    __slots__ = ("buffer", "count")

    def __init__(self, frame: CanFrame) -> None:
        self.buffer = frame.new_buffer()
        self.count = 0

    def next(self) -> bytearray:
        self.buffer[DATA_AT] = self.count
        self.count = (self.count + 1) & 0xFF
        return self.buffer


def frame_id_of(buffer: Any) -> int:
    """The SocketCAN id (with its flag bits) of a wire frame."""
    frame_id: int = HEADER.unpack_from(buffer, 0)[0]
    return frame_id
