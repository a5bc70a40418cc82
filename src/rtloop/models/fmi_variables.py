"""FMI variables as rtloop sees them: every scalar element mapped to a float64.

An FMU's ``u`` and ``y`` are float64 vectors, but its variables may be integers,
booleans, enumerations, Float32 or (FMI 3) arrays. This module flattens each variable
into elements (``x`` → ``x[0]``, ``x[1]``, … for an array), says which FMI type and
ctypes type carries it, and checks that a float64 converts to that type exactly
(integral, in range) — the round trip float64 → type → float64 is then exact.
"""

from __future__ import annotations

import ctypes
import math
from dataclasses import dataclass
from typing import Any

from rtloop.models.base import FmuError

# FMI type → (name of the FMI function suffix, ctypes type, lowest, highest); None: a float
_FMI3_TYPES: dict[str, tuple[str, Any, float | None, float | None]] = {
    "Float64": ("Float64", ctypes.c_double, None, None),
    "Float32": ("Float32", ctypes.c_float, None, None),
    "Int8": ("Int8", ctypes.c_int8, -(2**7), 2**7 - 1),
    "UInt8": ("UInt8", ctypes.c_uint8, 0, 2**8 - 1),
    "Int16": ("Int16", ctypes.c_int16, -(2**15), 2**15 - 1),
    "UInt16": ("UInt16", ctypes.c_uint16, 0, 2**16 - 1),
    "Int32": ("Int32", ctypes.c_int32, -(2**31), 2**31 - 1),
    "UInt32": ("UInt32", ctypes.c_uint32, 0, 2**32 - 1),
    # beyond 2**53 a float64 no longer holds every integer: the exact range is what we accept
    "Int64": ("Int64", ctypes.c_int64, -(2**53), 2**53),
    "UInt64": ("UInt64", ctypes.c_uint64, 0, 2**53),
    "Enumeration": ("Int64", ctypes.c_int64, -(2**53), 2**53),
    "Boolean": ("Boolean", ctypes.c_bool, 0, 1),
}
_FMI2_TYPES: dict[str, tuple[str, Any, float | None, float | None]] = {
    "Real": ("Real", ctypes.c_double, None, None),
    "Integer": ("Integer", ctypes.c_int, -(2**31), 2**31 - 1),
    "Enumeration": ("Integer", ctypes.c_int, -(2**31), 2**31 - 1),
    "Boolean": ("Boolean", ctypes.c_int, 0, 1),
}
UNSUPPORTED = ("String", "Binary", "Clock")


@dataclass(frozen=True, slots=True)
class Element:
    """One scalar of an FMI variable, as it sits in ``u`` or ``y``."""

    name: str
    """``x`` for a scalar, ``x[2]`` / ``x[1,0]`` for an array element."""
    variable: str
    """The FMI variable's name."""
    value_reference: int
    offset: int
    """Position of this element within the variable's values (row-major)."""
    fmi_type: str
    """As in the model description: Real, Float64, Int32, Boolean, Enumeration, ..."""
    function_type: str
    """Suffix of the FMI get/set functions that carry it (Real, Float64, Int64, ...)."""
    ctype: Any
    low: float | None
    high: float | None
    causality: str
    variability: str
    start: float | None

    def check(self, value: float) -> None:
        """Raise :class:`FmuError` if ``value`` does not convert exactly to this type."""
        if self.low is None or self.high is None:
            return
        if not math.isfinite(value) or value != math.floor(value) or not self.low <= value <= self.high:
            kind = "0 or 1" if self.fmi_type == "Boolean" else f"an integer in [{self.low:g}, {self.high:g}]"
            raise FmuError(f"{self.name} is {self.fmi_type}: {value!r} is not {kind}")


def type_table(fmi_version: str) -> dict[str, tuple[str, Any, float | None, float | None]]:
    return _FMI3_TYPES if fmi_version.startswith("3") else _FMI2_TYPES


def shape_of(variable: Any) -> tuple[int, ...]:
    """The array shape of an FMI 3 variable (``()`` for a scalar), dimensions resolved."""
    shape = getattr(variable, "shape", None)
    if shape:
        return tuple(int(n) for n in shape)
    dims = []
    for dimension in getattr(variable, "dimensions", None) or ():
        if dimension.start is not None:
            dims.append(int(dimension.start))
        elif dimension.variable is not None and dimension.variable.start is not None:
            dims.append(int(dimension.variable.start))
        else:
            raise FmuError(f"{variable.name}: array dimension without a size")
    return tuple(dims)


def _start_values(variable: Any, n: int) -> list[float | None]:
    text = variable.start
    if text is None:
        return [None] * n
    parts = str(text).split()
    values: list[float | None] = []
    for part in parts:
        lowered = part.lower()
        values.append(1.0 if lowered == "true" else 0.0 if lowered == "false" else float(part))
    if len(values) == 1 and n > 1:
        values = values * n
    return (values + [None] * n)[:n]


def elements_of(variable: Any, fmi_version: str) -> list[Element]:
    """The scalar elements of one model variable (raises for types rtloop cannot carry)."""
    table = type_table(fmi_version)
    if variable.type not in table:
        raise FmuError(f"{variable.name} is {variable.type}: rtloop carries numbers and booleans only")
    function_type, ctype, low, high = table[variable.type]
    shape = shape_of(variable) if fmi_version.startswith("3") else ()
    n = math.prod(shape) if shape else 1
    starts = _start_values(variable, n)
    out = []
    for offset in range(n):
        if shape:
            index, rest = [], offset
            for size in reversed(shape):
                index.append(rest % size)
                rest //= size
            name = f"{variable.name}[{','.join(str(i) for i in reversed(index))}]"
        else:
            name = variable.name
        out.append(Element(name, variable.name, variable.valueReference, offset, variable.type, function_type,
                           ctype, low, high, variable.causality or "local", variable.variability or "continuous",
                           starts[offset]))
    return out


def carried(variable: Any, fmi_version: str) -> bool:
    return variable.type in type_table(fmi_version)
