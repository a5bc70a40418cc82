"""Setpoint profiles: a CSV with a ``t_s`` column and one column per value, held piecewise constant."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.errors import AppError, ConnectionSizeError


def load_profile(path: Path, size: int, where: str,
                 value_range: tuple[Any, Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read a CSV profile: header ``t_s,...`` then rows; returns (t_ns, values).

    ``value_range``: the port's ``[lo, hi]`` (or one per value); a profile value outside it is refused as a
    live write would be (naming the file, the row and the column).
    """
    try:
        with open(path, newline="") as file:
            rows = list(csv.reader(file))
    except OSError as error:
        raise AppError(f"{where}: cannot read profile {path}: {error.strerror}") from None
    if not rows or not rows[0] or rows[0][0].strip() != "t_s":
        raise AppError(f"{where}: {path}: the first column must be named t_s")
    header = rows[0]
    if len(header) - 1 != size:
        raise ConnectionSizeError(
            f"{where}: {path} has {len(header) - 1} value columns {header[1:]}, the port takes {size}"
        )
    times: list[int] = []
    values: list[list[float]] = []
    for line_number, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        try:
            numbers = [float(cell) for cell in row]
        except ValueError:
            raise AppError(f"{where}: {path}:{line_number}: not a number in {row}") from None
        if len(numbers) != len(header):
            raise AppError(f"{where}: {path}:{line_number}: {len(numbers)} columns, header has {len(header)}")
        if not all(np.isfinite(numbers)):
            raise AppError(f"{where}: {path}:{line_number}: NaN or infinite value in {row}")
        if value_range is not None:
            for index, (column, value) in enumerate(zip(header[1:], numbers[1:], strict=True)):
                low, high = (bound[index] if isinstance(bound, tuple) else bound for bound in value_range)
                if not low <= value <= high:
                    raise AppError(f"{where}: {path}:{line_number}: column {column.strip()!r} is {value!r}, outside "
                                   f"the port's range [{low!r}, {high!r}]")
        t_ns = round(numbers[0] * 1e9)
        if times and t_ns <= times[-1]:
            raise AppError(f"{where}: {path}:{line_number}: t_s must increase")
        times.append(t_ns)
        values.append(numbers[1:])
    if not times:
        raise AppError(f"{where}: {path}: no rows")
    return np.array(times, dtype=np.int64), np.array(values, dtype=np.float64).reshape(len(times), size)
