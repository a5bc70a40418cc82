"""Values headed for a port, checked the same way whoever sends them.

``rtloop port write`` and :meth:`RunningApp.write <rtloop.ipc.ports.RunningApp.write>`, a
ROS 2 bridge and the Foxglove live view all pass what they receive through
:func:`validate_values` before it reaches a real-time task: a value of the wrong size, a
string, a NaN headed for a motor or a value outside the port's range never gets there.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rtloop.errors import PortValueError
from rtloop.text import shorten

REASONS = ("type", "shape", "length", "nonfinite", "range")
"""Why values can be refused: not numbers, not flat, wrong length, NaN or inf, outside the range."""


class RejectedValues(PortValueError):
    """Values refused by :func:`validate_values`; ``reason`` is one of :data:`REASONS`."""

    def __init__(self, reason: str, message: str) -> None:
        self.reason = reason
        super().__init__(message)

    def __reduce__(self) -> tuple[Any, ...]:
        return type(self), (self.reason, str(self))


def validate_values(values: Any, size: int, *, allow_nonfinite: bool = False, where: str = "value",
                    value_range: tuple[Any, Any] | None = None) -> np.ndarray:
    """``values`` as a new flat float64 array of ``size`` numbers, or :class:`RejectedValues` naming what is wrong.

    Only ints and floats count as numbers (numpy would otherwise read ``"1.5"`` or ``True``);
    a single number stands for one value. NaN and ±inf are refused unless ``allow_nonfinite``
    (one NaN fed back into a controller makes every later output NaN); with ``value_range``
    ``(lo, hi)`` (numbers, or sequences with one bound per value), a value outside it is refused
    (a NaN, when allowed, passes).
    """
    try:
        raw = np.asarray(values)
    except (TypeError, ValueError, OverflowError):  # ragged nested sequences, odd objects
        raw = np.empty(0, dtype=object)
    if raw.dtype.kind not in "iuf":
        raise RejectedValues("type", f"{where}: expected numbers, got {shorten(values, 60)}")
    array = raw.astype(np.float64).reshape(-1) if raw.ndim == 0 else raw.astype(np.float64)  # always a copy
    if array.ndim != 1:
        raise RejectedValues("shape", f"{where}: expected a flat sequence of {size} numbers, got shape {array.shape}")
    if array.size != size:
        raise RejectedValues("length", f"{where}: takes {size} value{'s' if size != 1 else ''}, got {array.size}")
    if not allow_nonfinite:
        bad = np.flatnonzero(~np.isfinite(array))
        if bad.size:
            raise RejectedValues("nonfinite", f"{where}: NaN or infinite value at index {shorten(bad.tolist())} of "
                                 f"{shorten(array.tolist())}")
    if value_range is not None:
        low, high = (np.broadcast_to(np.asarray(bound, dtype=np.float64), array.shape) for bound in value_range)
        outside = np.flatnonzero(~((array >= low) & (array <= high)) & ~np.isnan(array))
        if outside.size:
            first = int(outside[0])
            raise RejectedValues("range", f"{where}: value {float(array[first])!r} at index {first} is outside its "
                                 f"range [{float(low[first])!r}, {float(high[first])!r}]")
    return array
