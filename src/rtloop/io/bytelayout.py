"""Signals packed into the bytes of a frame: a CAN frame's data, an SPI frame's payload.

A frame is declared as a list of fields, each a number at a byte offset with a type, a byte
order and a scale and offset (``value = raw * scale + offset``, the convention of CAN
databases). The layout is checked once, when the app is loaded (does every field fit the
frame, do two fields overlap, is the scale usable), and then packs and unpacks without
allocating anything that outlives the call: a ``struct.Struct`` per field, compiled once.

Packing rounds to the nearest raw integer (ties to even) and saturates at the type's range:
a command too large for its field is sent as the largest value the field holds, never
wrapped round to the other sign. A non-finite value is refused (``ValueError`` naming the
field): a NaN never reaches a wire.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from rtloop.errors import AppError
from rtloop.io.compiled import devio
from rtloop.io.device import MAX_SETTING_MAGNITUDE, number_problem

# type name -> (struct code, is integer)
FIELD_TYPES: dict[str, tuple[str, bool]] = {
    "u8": ("B", True), "i8": ("b", True), "u16": ("H", True), "i16": ("h", True),
    "u32": ("I", True), "i32": ("i", True), "u64": ("Q", True), "i64": ("q", True),
    "f32": ("f", False), "f64": ("d", False),
}
BYTE_ORDERS = {"little": "<", "big": ">"}


class LayoutError(AppError):
    """A frame's declared layout is impossible (names the place in the declaration)."""


@dataclass(frozen=True, slots=True)
class Field:
    """One number in a frame: ``value = raw * scale + offset``."""

    name: str
    start_byte: int
    type: str = "i16"
    scale: float = 1.0
    offset: float = 0.0
    byte_order: str = "little"

    @property
    def size_bytes(self) -> int:
        return struct.calcsize(FIELD_TYPES[self.type][0])

    @property
    def raw_range(self) -> tuple[float, float]:
        """The smallest and largest raw value the field holds."""
        code, integer = FIELD_TYPES[self.type]
        if not integer:
            largest = 3.4028234663852886e38 if code == "f" else 1.7976931348623157e308
            return -largest, largest
        bits = 8 * self.size_bytes
        if code.isupper():
            return 0, (1 << bits) - 1
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1

    @property
    def value_range(self) -> tuple[float, float]:
        """The smallest and largest value (in the signal's unit) the field can carry."""
        low, high = (raw * self.scale + self.offset for raw in self.raw_range)
        return (low, high) if low <= high else (high, low)


def field_from_table(table: Mapping[str, Any], where: str) -> Field:
    """A :class:`Field` from its app-file table (``{name, start_byte, type, scale, offset, byte_order}``)."""
    known = {"name", "start_byte", "type", "scale", "offset", "byte_order"}
    unknown = sorted(set(table) - known)
    if unknown:
        raise LayoutError(f"{where}: unknown key {unknown[0]!r} (a field has {', '.join(sorted(known))})")
    name = table.get("name")
    if not isinstance(name, str) or not name:
        raise LayoutError(f"{where}.name: expected a non-empty string")
    start = table.get("start_byte")
    if not isinstance(start, int) or isinstance(start, bool) or start < 0:
        raise LayoutError(f"{where}.start_byte: expected an integer >= 0, got {start!r}")
    kind = table.get("type", "i16")
    if kind not in FIELD_TYPES:
        raise LayoutError(f"{where}.type: expected one of {', '.join(FIELD_TYPES)}, got {kind!r}")
    order = table.get("byte_order", "little")
    if order not in BYTE_ORDERS:
        raise LayoutError(f"{where}.byte_order: expected 'little' or 'big', got {order!r}")
    numbers = {}
    for key, default in (("scale", 1.0), ("offset", 0.0)):
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise LayoutError(f"{where}.{key}: expected a finite number, got {value!r}")
        problem = number_problem(value)
        if problem:
            raise LayoutError(f"{where}.{key}: {problem}")
        numbers[key] = float(value)
    if numbers["scale"] == 0.0:
        raise LayoutError(f"{where}.scale: must not be 0 (value = raw * scale + offset)")
    if abs(numbers["scale"]) < 1 / MAX_SETTING_MAGNITUDE:  # a command divided by it would overflow to inf
        raise LayoutError(f"{where}.scale: must be at least {1 / MAX_SETTING_MAGNITUDE:g} in size, "
                          f"got {numbers['scale']!r}")
    return Field(name, start, kind, numbers["scale"], numbers["offset"], order)


class ByteLayout:
    """Fields at fixed places in a frame of ``size_bytes``; packs and unpacks floats."""

    def __init__(self, fields: Sequence[Field], size_bytes: int, where: str) -> None:
        self.fields = tuple(fields)
        self.size_bytes = size_bytes
        self.where = where
        taken: dict[int, str] = {}
        names: set[str] = set()
        for index, field in enumerate(self.fields):
            at = f"{where}[{index}] ({field.name!r})"
            if field.name in names:
                raise LayoutError(f"{at}: the name {field.name!r} is used twice in this frame")
            names.add(field.name)
            end = field.start_byte + field.size_bytes
            if end > size_bytes:
                raise LayoutError(f"{at}: a {field.type} at byte {field.start_byte} ends at byte {end}, "
                                  f"past the frame's {size_bytes} bytes: the layout does not fit the frame")
            for byte in range(field.start_byte, end):
                if byte in taken:
                    raise LayoutError(f"{at}: byte {byte} is also used by {taken[byte]!r}")
                taken[byte] = field.name
        # (codec, byte offset, scale, offset, raw low, raw high, is integer), compiled once.
        self._plan = tuple(
            (struct.Struct(BYTE_ORDERS[f.byte_order] + FIELD_TYPES[f.type][0]), f.start_byte, f.scale, f.offset,
             *f.raw_range, FIELD_TYPES[f.type][1])
            for f in self.fields)
        compiled = devio()  # the same packing in C (io/_devio.c), where it was built
        self._compiled = compiled.Layout([(FIELD_TYPES[f.type][0], f.start_byte, f.scale, f.offset,
                                           f.byte_order == "big") for f in self.fields]) if compiled else None

    def __len__(self) -> int:
        return len(self.fields)

    def __reduce__(self) -> tuple[Any, ...]:
        # compiled struct codecs do not pickle: a layout travels to the task process as its declaration
        return ByteLayout, (self.fields, self.size_bytes, self.where)

    @property
    def names(self) -> list[str]:
        return [field.name for field in self.fields]

    def pack_into(self, frame: Any, at: int, values: Any, first: int = 0) -> None:
        """Write ``values[first:first + len(self)]`` into ``frame`` (a writable buffer) from byte ``at``."""
        if self._compiled is not None:
            try:
                bad = self._compiled.pack_into(frame, at, values, first)
            except TypeError:  # not a float64 vector (a list): the Python way below
                pass
            else:
                if bad >= 0:
                    raise ValueError(self._not_finite(bad, values[first + bad]))
                return
        index = first
        try:
            for codec, start, scale, offset, low, high, integer in self._plan:
                raw = (values[index] - offset) / scale
                if integer:
                    raw = round(raw)  # NaN and ±inf raise here: never sent
                    if raw > high:
                        raw = high
                    elif raw < low:
                        raw = low
                elif raw - raw != 0.0:  # NaN or ±inf (inf - inf is NaN); 0.0 for every finite value
                    raise ValueError
                codec.pack_into(frame, at + start, raw)
                index += 1
        except (ValueError, OverflowError):
            raise ValueError(self._not_finite(index - first, values[index])) from None

    def unpack_from(self, frame: Any, at: int, out: Any, first: int = 0) -> None:
        """Read the fields of ``frame`` (from byte ``at``) into ``out[first:first + len(self)]``."""
        if self._compiled is not None:
            try:
                self._compiled.unpack_from(frame, at, out, first)
                return
            except TypeError:  # not a float64 vector: the Python way below
                pass
        index = first
        for codec, start, scale, offset, _low, _high, _integer in self._plan:
            out[index] = codec.unpack_from(frame, at + start)[0] * scale + offset
            index += 1

    def round_trip(self, values: Any, out: Any, first: int = 0) -> None:
        """What the other end reads when ``values`` are packed: the layout's rounding and saturation.

        A twin uses it so a simulation sees the numbers the wire would have carried."""
        scratch = bytearray(self.size_bytes)
        self.pack_into(scratch, 0, values, first)
        self.unpack_from(scratch, 0, out, first)

    def _not_finite(self, index: int, value: float) -> str:
        return f"{self.where}: {self.fields[index].name!r} is {value!r}: a non-finite value is never sent"


class FloatView:
    """A memoryview of the vector a driver is handed every cycle, made again only when the vector changes.

    A driver gets the same numpy arrays each cycle; indexing a memoryview of one gives a Python
    float in a third of the time numpy takes to make a numpy scalar, and nothing is left behind."""

    __slots__ = ("array", "view")

    def __init__(self) -> None:
        self.array: Any = None
        self.view: Any = None

    def of(self, array: Any) -> Any:
        if array is not self.array:
            self.array = array
            self.view = memoryview(array) if getattr(array, "dtype", None) == "float64" else array
        return self.view
