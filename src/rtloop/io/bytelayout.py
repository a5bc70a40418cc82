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

Two kinds of field carry a signal rather than a number:

- an **encoder**, ``encoder = { counts_per_rev = 4096, gear_ratio = 50 }`` on an integer field:
  a counter that wraps (a 16- or 32-bit encoder count) read as the position in rad of the
  output shaft (``counts_per_rev × gear_ratio`` counts a turn, plus ``offset`` rad), unwrapped:
  the layout keeps the count it read last and adds each change, taken the short way round the
  counter's range (the counter must move less than half its range between two reads). The
  first read starts from the count as it is. Packed (a twin's side), a position goes out as
  its count, wrapped into the field's range, as the hardware's counter would show it;
- a **duty**, ``duty = { full_scale = 1000, range = [-1.0, 1.0] }``: a PWM duty cycle, sent as
  ``duty × full_scale`` (the PWM generator's period in counts) and clamped to ``range`` first:
  whatever the command, no more than the declared duty reaches the wire.

Neither takes a ``scale`` (the encoder and the full scale say it). Both run in C where it was
built (``io/devio_c/bytelayout.c``: the encoders' counts kept there, the duty's clamp), bit for
bit as the Python below, so the SPI and CAN cycles that use them stay one C call; a 64-bit
encoder (its unsigned count would outgrow C's int64) runs in Python.
"""

from __future__ import annotations

import math
import struct
from array import array
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
    counts_per_turn: float = 0.0
    """An encoder (see the module): counts per turn of the output (counts per rev × gear ratio); 0: not one."""
    duty_range: tuple[float, float] | None = None
    """A duty (see the module): the duty's [min, max], ``scale`` being 1 / full scale; None: not one."""

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
    """A :class:`Field` from its app-file table (``{name, start_byte, type, scale, offset, byte_order}``,
    or ``encoder``/``duty`` in place of ``scale``)."""
    known = {"name", "start_byte", "type", "scale", "offset", "byte_order", "encoder", "duty"}
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
    if "encoder" in table and "duty" in table:
        raise LayoutError(f"{where}: a field is an encoder or a duty, not both")
    if ("encoder" in table or "duty" in table) and "scale" in table:
        raise LayoutError(f"{where}.scale: not with {'encoder' if 'encoder' in table else 'duty'} "
                          "(it says the scale)")
    field = Field(name, start, kind, numbers["scale"], numbers["offset"], order)
    if "encoder" in table:
        return _encoder_field(field, table["encoder"], f"{where}.encoder")
    if "duty" in table:
        return _duty_field(field, table["duty"], f"{where}.duty")
    return field


def _positive(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise LayoutError(f"{where}: expected a number > 0, got {value!r}")
    problem = number_problem(value)
    if problem:
        raise LayoutError(f"{where}: {problem}")
    return float(value)


def _encoder_field(field: Field, table: Any, where: str) -> Field:
    if not isinstance(table, Mapping) or set(table) - {"counts_per_rev", "gear_ratio"} or "counts_per_rev" not in table:
        raise LayoutError(f"{where}: expected {{ counts_per_rev = 4096, gear_ratio = 1.0 }}, got {table!r}")
    if not FIELD_TYPES[field.type][1]:
        raise LayoutError(f"{where}: an encoder counts: its type is an integer (u16, i32, ...), not {field.type}")
    counts = _positive(table["counts_per_rev"], f"{where}.counts_per_rev")
    ratio = _positive(table.get("gear_ratio", 1.0), f"{where}.gear_ratio")
    per_turn = counts * ratio
    return Field(field.name, field.start_byte, field.type, 2 * math.pi / per_turn, field.offset, field.byte_order,
                 counts_per_turn=per_turn)


def _duty_field(field: Field, table: Any, where: str) -> Field:
    if not isinstance(table, Mapping) or set(table) - {"full_scale", "range"} or "full_scale" not in table:
        raise LayoutError(f"{where}: expected {{ full_scale = 1000, range = [-1.0, 1.0] }}, got {table!r}")
    if field.offset:
        raise LayoutError(f"{where}: a duty has no offset (0 is no drive)")
    full_scale = _positive(table["full_scale"], f"{where}.full_scale")
    bounds = table.get("range", [-1.0, 1.0])
    if not isinstance(bounds, list | tuple) or len(bounds) != 2 or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in bounds) \
            or not bounds[0] < bounds[1] or abs(bounds[0]) > 1 or abs(bounds[1]) > 1:
        raise LayoutError(f"{where}.range: expected [min, max] within [-1, 1], min < max, got {bounds!r}")
    low, high = Field(field.name, 0, field.type).raw_range
    if bounds[0] * full_scale < low or bounds[1] * full_scale > high:
        raise LayoutError(f"{where}: {bounds[0]:g}..{bounds[1]:g} × full_scale {full_scale:g} does not fit a "
                          f"{field.type} ({low:g}..{high:g})")
    return Field(field.name, field.start_byte, field.type, 1.0 / full_scale, 0.0, field.byte_order,
                 duty_range=(float(bounds[0]), float(bounds[1])))


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
             *_sent_range(f), FIELD_TYPES[f.type][1])
            for f in self.fields)
        # encoders: (index, counter span) and, per encoder, the count read last and the unwrapped total
        self._encoders = tuple((i, int(f.raw_range[1] - f.raw_range[0] + 1)) for i, f in enumerate(self.fields)
                               if f.counts_per_turn)
        self._last_count: list[int | None] = [None] * len(self.fields)
        self._total_count = [0] * len(self.fields)
        self._float_duties = any(f.duty_range is not None and not FIELD_TYPES[f.type][1] for f in self.fields)
        # the same packing in C (io/_devio.c), where it was built; encoders and duties too, bit for bit
        # (a 64-bit encoder's unsigned count would outgrow the C int64 it is kept in: Python's)
        wide = any(f.counts_per_turn and f.size_bytes == 8 for f in self.fields)
        compiled = None if wide else devio()
        self._compiled = compiled.Layout([(FIELD_TYPES[f.type][0], f.start_byte, f.scale, f.offset,
                                           f.byte_order == "big", bool(f.counts_per_turn),
                                           *(_sent_range(f) if f.duty_range is not None else (-math.inf, math.inf)))
                                          for f in self.fields]) if compiled else None
        # where the encoders' counts live in C, a reading into a list goes through this (one count per encoder)
        self._scratch = array("d", bytes(8 * len(self.fields))) if self._compiled and self._encoders else None

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
                    if self._encoders and self.fields[index - first].counts_per_turn:
                        raw = (raw - low) % (high - low + 1) + low  # a counter shows the count wrapped
                    elif raw > high:
                        raw = high
                    elif raw < low:
                        raw = low
                elif raw - raw != 0.0:  # NaN or ±inf (inf - inf is NaN); 0.0 for every finite value
                    raise ValueError
                elif self._float_duties and self.fields[index - first].duty_range is not None:
                    raw = min(max(raw, low), high)  # a float duty: its range
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
                scratch = self._scratch
                if scratch is not None:  # the encoders' counts are kept in C: read there, then copied
                    self._compiled.unpack_from(frame, at, scratch, 0)
                    for index, value in enumerate(scratch):
                        out[first + index] = value
                    return
        index = first
        for codec, start, scale, offset, _low, _high, _integer in self._plan:
            out[index] = codec.unpack_from(frame, at + start)[0] * scale + offset
            index += 1
        for field_index, span in self._encoders:  # counts → the unwrapped position
            count = self._plan[field_index][0].unpack_from(frame, at + self._plan[field_index][1])[0]
            last = self._last_count[field_index]
            if last is None:
                total = count
            else:
                step = (count - last) % span
                total = self._total_count[field_index] + (step - span if step >= span // 2 else step)
            self._last_count[field_index] = count
            self._total_count[field_index] = total
            field = self.fields[field_index]
            out[first + field_index] = total * field.scale + field.offset

    def round_trip(self, values: Any, out: Any, first: int = 0) -> None:
        """What the other end reads when ``values`` are packed: the layout's rounding and saturation.

        A twin uses it so a simulation sees the numbers the wire would have carried."""
        scratch = bytearray(self.size_bytes)
        self.pack_into(scratch, 0, values, first)
        self.unpack_from(scratch, 0, out, first)

    def _not_finite(self, index: int, value: float) -> str:
        return f"{self.where}: {self.fields[index].name!r} is {value!r}: a non-finite value is never sent"


def _sent_range(field: Field) -> tuple[float, float]:
    """The raw values a field may be sent as: its type's range, or its duty's."""
    if field.duty_range is None:
        return field.raw_range
    low, high = field.duty_range[0] / field.scale, field.duty_range[1] / field.scale
    if FIELD_TYPES[field.type][1]:  # an integer field: the counts within the range
        return math.ceil(low - 1e-9), math.floor(high + 1e-9)
    return low, high


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
