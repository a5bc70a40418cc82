"""Will a whole recording fit on the disk? Bytes per second estimated from what the app records,
before a run with ``--duration`` (and no ``--keep``) starts keeping everything.

The estimate errs high (a refusal costs a re-run with ``--keep``; a full disk costs the end of
the run, where its fault is, and every other user's room): a timing row per task and cycle in
timing.csv and run.mcap, and a row of every recorded value per cycle of the fastest recorded
task in signals.csv and run.mcap. inputs.csv and reads.csv (rows only when a value comes in or
a read is stale) are left out. The DC motor example is estimated at 0.49 MB/s; it writes
0.31 MB/s (measured: a 4-s run).
"""

from __future__ import annotations

import os
from pathlib import Path

from rtloop.app.builder import App
from rtloop.errors import AppError

TIMING_BYTES_PER_CYCLE = 120
"""A timing.csv row (task, cycle, three stamps of up to 19 digits: ≤ 80 characters) and its run.mcap record."""
ROW_BYTES = 60
"""A signals.csv row's time and line end, and the header of its run.mcap message."""
VALUE_BYTES = 32
"""One value in signals.csv (a double's shortest repr: ≤ 24 characters) and in run.mcap (8 bytes)."""


def recording_bytes_per_s(app: App) -> float:
    """Bytes the recording of ``app`` grows by per second of run time (an estimate that errs high)."""
    rates_hz = {name: 1e9 / task.config.period_ns for name, task in app.tasks.items()}
    timing = sum(rates_hz.values()) * TIMING_BYTES_PER_CYCLE
    values = sum(ref.size for ref in app.recorded)
    rows_per_s = max((rates_hz[ref.task] for ref in app.recorded), default=0.0)
    return timing + rows_per_s * (ROW_BYTES + VALUE_BYTES * values) if values else timing


def free_bytes(out: Path) -> int | None:
    """Free bytes (for an unprivileged user) on the file system ``out`` is or will be made on."""
    folder = Path(os.path.abspath(out))
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        stats = os.statvfs(folder)
    except OSError:
        return None  # the folder check that follows says what is wrong with it
    if stats.f_blocks == 0:
        return None  # no disk under it (/proc, /sys): making the folder fails, and says so
    return stats.f_bavail * stats.f_frsize


def check_room(app: App, out: Path, duration_s: float, free: int | None = None, *, what: str = "",
               remedy: str = "") -> None:
    """Refuse a recording of ``duration_s`` that would not fit in the free space at ``out``.

    ``what`` records (default: ``--duration S s``); ``remedy`` says what to do instead
    (default: ``--keep S``, with the S that fits)."""
    free = free_bytes(out) if free is None else free
    if free is None:
        return
    per_s = recording_bytes_per_s(app)
    needed = per_s * duration_s
    if needed > free:
        fits_s = max(1, int(free / per_s / 4))  # --keep S holds up to ≈ 3.3·S s, and a copy of run.mcap at the end
        remedy = remedy or (f"keep the last S seconds only with --keep S (up to --keep {fits_s} fits), or give a "
                            "shorter --duration")
        raise AppError(f"{what or f'--duration {duration_s:.15g} s'} would record about {_size(needed)} "
                       f"({_size(per_s)}/s, an estimate that errs high) and {out} has {_size(free)} free: {remedy}")


def _size(size_bytes: float) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if size_bytes >= scale:
            return f"{size_bytes / scale:.1f} {unit}"
    return f"{size_bytes:.0f} B"
