"""Setpoint profiles: a CSV with a ``t_s`` column and one column per value, held piecewise constant.

A profile is read whole before the run starts, so its file is bounded: a regular file of at
most :data:`MAX_PROFILE_BYTES`. ``/dev/zero`` would fill the memory, a FIFO would hang the
start: both are refused in one line naming the port and the path, when the app loads.
"""

from __future__ import annotations

import csv
import io
import math
import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.errors import AppError, ConnectionSizeError
from rtloop.seconds import ns_from_seconds

MAX_PROFILE_BYTES = 64 << 20
"""64 MiB: hours of a 1 kHz profile; parsing one this large holds about 0.4 GB for a moment."""
MAX_PROFILE_TIME_S = 1e9
"""A row's ``t_s`` at most this far from 0 (about 31 years; nanoseconds fit an int64)."""


def check_profile_file(path: str | os.PathLike[str], where: str) -> None:
    """Refuse a feed that is there but is not a regular file, or is too large to be a profile.

    A path not there (yet) is left to :func:`load_profile`, which says so when the run starts."""
    try:
        info = os.stat(path)
    except OSError:
        return
    _check_file(info, path, where)


def _check_file(info: os.stat_result, path: str | os.PathLike[str], where: str) -> None:
    if not stat.S_ISREG(info.st_mode):
        kind = "a directory" if stat.S_ISDIR(info.st_mode) else "not a regular file"
        raise AppError(f"{where}: {os.fspath(path)} is {kind} (a profile feed is a CSV file)")
    if info.st_size > MAX_PROFILE_BYTES:
        raise AppError(f"{where}: {os.fspath(path)} has {info.st_size} bytes; a profile feed has at most "
                       f"{MAX_PROFILE_BYTES} ({MAX_PROFILE_BYTES >> 20} MiB)")


def _read_bounded(path: Path, where: str) -> str:
    """The file's text; never waits on a FIFO and never reads past the bound (the file may have
    been swapped since the app loaded)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as error:
        raise AppError(f"{where}: cannot read profile {path}: {error.strerror}") from None
    with open(fd, "rb") as file:
        _check_file(os.fstat(fd), path, where)
        try:
            raw = file.read(MAX_PROFILE_BYTES + 1)
        except OSError as error:
            raise AppError(f"{where}: cannot read profile {path}: {error.strerror}") from None
    if len(raw) > MAX_PROFILE_BYTES:
        raise AppError(f"{where}: {path} grew past {MAX_PROFILE_BYTES} bytes; a profile feed has at most that")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as error:
        raise AppError(f"{where}: {path}: not UTF-8 text (byte {error.start}); a profile is a CSV file") from None


def _rows(text: str, path: Path, where: str) -> Iterator[list[str]]:
    """The CSV rows; a malformed one (a NUL byte, a field of 128 kB) is the file's error, not ours."""
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        yield from reader
    except csv.Error as error:
        raise AppError(f"{where}: {path}:{reader.line_num}: not CSV: {error}") from None


def load_profile(path: Path, size: int, where: str,
                 value_range: tuple[Any, Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read a CSV profile: header ``t_s,...`` then rows; returns (t_ns, values).

    ``value_range``: the port's ``[lo, hi]`` (or one per value); a profile value outside it is refused as a
    live write would be (naming the file, the row and the column).
    """
    text = _read_bounded(Path(path), where)
    rows = _rows(text, path, where)
    header = next(rows, [])
    if not header or header[0].strip() != "t_s":
        raise AppError(f"{where}: {path}: the first column must be named t_s")
    if len(header) - 1 != size:
        raise ConnectionSizeError(
            f"{where}: {path} has {len(header) - 1} value columns {header[1:]}, the port takes {size}"
        )
    most_rows = text.count("\n") + 1  # arrays filled in place: a long profile holds no Python list per row
    times = np.empty(most_rows, dtype=np.int64)
    values = np.empty((most_rows, size), dtype=np.float64)
    count = 0
    for line_number, row in enumerate(rows, start=2):
        if not row:
            continue
        try:
            numbers = [float(cell) for cell in row]
        except ValueError:
            raise AppError(f"{where}: {path}:{line_number}: not a number in {row}") from None
        if len(numbers) != len(header):
            raise AppError(f"{where}: {path}:{line_number}: {len(numbers)} columns, header has {len(header)}")
        if not all(math.isfinite(number) for number in numbers):
            raise AppError(f"{where}: {path}:{line_number}: NaN or infinite value in {row}")
        if abs(numbers[0]) > MAX_PROFILE_TIME_S:
            raise AppError(f"{where}: {path}:{line_number}: t_s is {numbers[0]!r}; at most {MAX_PROFILE_TIME_S:g} s")
        if value_range is not None:
            for index, (column, value) in enumerate(zip(header[1:], numbers[1:], strict=True)):
                low, high = (bound[index] if isinstance(bound, tuple) else bound for bound in value_range)
                if not low <= value <= high:
                    raise AppError(f"{where}: {path}:{line_number}: column {column.strip()!r} is {value!r}, outside "
                                   f"the port's range [{low!r}, {high!r}]")
        t_ns = ns_from_seconds(row[0])  # exactly: a float's nanoseconds drift after 104 days
        if count and t_ns <= times[count - 1]:
            raise AppError(f"{where}: {path}:{line_number}: t_s must increase")
        times[count] = t_ns
        values[count] = numbers[1:]
        count += 1
    if not count:
        raise AppError(f"{where}: {path}: no rows")
    return times[:count].copy(), values[:count].copy()
