"""CDR (XCDR1, little endian) encoding of the few ROS 2 messages rtloop sends, without a DDS library.

The bytes are what a ROS 2 node puts on the wire: a 4-byte encapsulation header
(``00 01 00 00``), then each field aligned to its own size, counted from after the
header; strings are a length (with the NUL), the bytes and a NUL; sequences a count and
the elements. Used by the listener (a few µs a message instead of the generic
serialiser's ~40 µs) and by the Foxglove live view, which needs no DDS at all.
Tests compare every encoder with cyclonedds's own serialiser, byte for byte.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence

NS_PER_S = 1_000_000_000
ENCAPSULATION_LE = b"\x00\x01\x00\x00"


class CdrWriter:
    """Appends fields to one message; :meth:`bytes` returns it, padded to 4 bytes as DDS sends it."""

    def __init__(self) -> None:
        self.buffer = bytearray(ENCAPSULATION_LE)

    def align(self, size: int) -> None:
        self.buffer += bytes(-(len(self.buffer) - 4) % size)

    def u32(self, value: int) -> None:
        self.align(4)
        self.buffer += struct.pack("<I", value)

    def i32(self, value: int) -> None:
        self.align(4)
        self.buffer += struct.pack("<i", value)

    def u64(self, value: int) -> None:
        self.align(8)
        self.buffer += struct.pack("<Q", value)

    def i64(self, value: int) -> None:
        self.align(8)
        self.buffer += struct.pack("<q", value)

    def f64(self, value: float) -> None:
        self.align(8)
        self.buffer += struct.pack("<d", value)

    def string(self, text: str) -> None:
        data = text.encode()
        self.u32(len(data) + 1)
        self.buffer += data + b"\x00"

    def strings(self, texts: Sequence[str]) -> None:
        self.u32(len(texts))
        for text in texts:
            self.string(text)

    def f64s(self, values: Sequence[float]) -> None:
        self.u32(len(values))
        if values:
            self.align(8)
            self.buffer += struct.pack(f"<{len(values)}d", *values)

    def stamp(self, wall_ns: int) -> None:
        """``builtin_interfaces/Time`` of a wall-clock time in ns."""
        sec, nanosec = divmod(wall_ns, NS_PER_S)
        self.i32(sec)
        self.u32(nanosec)

    def bytes(self) -> bytes:
        self.buffer += bytes(-len(self.buffer) % 4)
        return bytes(self.buffer)


def joint_state_cdr(names: Sequence[str], positions: Sequence[float], stamp_ns: int, frame_id: str = "") -> bytes:
    """``sensor_msgs/msg/JointState`` with names and positions (no velocity, no effort)."""
    writer = CdrWriter()
    writer.stamp(stamp_ns)
    writer.string(frame_id)
    writer.strings(names)
    writer.f64s(positions)
    writer.f64s(())
    writer.f64s(())
    return writer.bytes()


def float64_multi_array_cdr(values: Sequence[float], label: str = "") -> bytes:
    """``std_msgs/msg/Float64MultiArray``: an empty layout, or one dimension named ``label``."""
    writer = CdrWriter()
    writer.u32(1 if label else 0)
    if label:
        writer.string(label)
        writer.u32(len(values))
        writer.u32(len(values))
    writer.u32(0)  # data_offset
    writer.f64s(values)
    return writer.bytes()


def float64_cdr(value: float) -> bytes:
    """``std_msgs/msg/Float64``."""
    writer = CdrWriter()
    writer.f64(value)
    return writer.bytes()


def cycle_timing_cdr(cycle: int, release_ns: int, start_ns: int, end_ns: int) -> bytes:
    """``rtloop_msgs/msg/CycleTiming`` (the schema run.mcap embeds)."""
    writer = CdrWriter()
    writer.u64(cycle)
    for value in (release_ns, start_ns, end_ns, start_ns - release_ns, end_ns - start_ns):
        writer.i64(value)
    return writer.bytes()


def encoder_for(msg_type: str, joint_names: Sequence[str] = ()) -> Callable[[Sequence[float], int], bytes]:
    """``encode(values, stamp_ns) -> bytes`` for one of the bridged ROS 2 types (as ``bridge.message_for``)."""
    if msg_type == "sensor_msgs/msg/JointState":
        names = tuple(joint_names)
        return lambda values, stamp_ns: joint_state_cdr(names or tuple(f"joint{i}" for i in range(len(values))),
                                                        values, stamp_ns)
    if msg_type == "std_msgs/msg/Float64":
        return lambda values, stamp_ns: float64_cdr(float(values[0]))
    return lambda values, stamp_ns: float64_multi_array_cdr(values)
