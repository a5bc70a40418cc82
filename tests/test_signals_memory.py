"""signals.csv's rows in memory are bounded by the slowest task's cycle in progress, not its period (issue 29)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from rtloop.app.specs import SignalRef
from rtloop.record.csvfiles import SignalsCsv


def test_a_slow_task_beside_a_fast_one_holds_back_only_its_cycle_in_progress(tmp_path: Path) -> None:
    """signals.csv's rows waited for every stream's next row: a 1-hour task beside a 1 kHz one held
    3.6 M rows in memory. A stream's next row comes a period after its newest at the earliest, so the
    fast task's rows are written as they come, up to the slow task's next release."""
    hour_ns, ms_ns = 3_600_000_000_000, 1_000_000
    path = tmp_path / "signals.csv"
    writer = SignalsCsv(path, [SignalRef("slow", "u", 0, 1), SignalRef("slow", "y", 0, 1),
                               SignalRef("fast", "y", 0, 1)], {"slow": hour_ns, "fast": ms_ns},
                        {"slow": 1, "fast": 1})
    writer.add("slow", np.array([-1, 0]), np.array([[0.0, 0.0], [1.0, 5.0]]))  # rows: y, then u
    written = 0
    for block in range(10):  # 10 s of the fast task, its rows drained every second
        ticks = block * 1000 + np.arange(1000) - (1 if block == 0 else 0)
        writer.add("fast", ticks, ticks[:, None].astype(np.float64))
        times, _ = writer.flush()
        written += len(times)
    pending = sum(len(b[0]) for blocks in writer.pending.values() for b in blocks)
    assert written >= 9_999 and pending <= 2, (written, pending)
    writer.flush(final=True)
    writer.close()
    with open(path, newline="") as file:
        rows = list(csv.reader(file))
    assert rows[1] == ["0.0", "5.0", "0.0", "-1.0"]  # from 0: the slow u of tick 0, both initial outputs
    assert rows[-1][:3] == ["3600.0", "5.0", "1.0"]  # the slow task's y of tick 0, from its next release
