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


def test_past_its_bound_a_task_waits_in_its_queue_while_the_one_waited_for_has_room(
        tmp_path: Path, monkeypatch) -> None:
    """By construction: rows held back never pass MAX_PENDING_VALUES. A task over its share is not
    drained (its rows wait in shared memory; an overflow there is a counted gap); the task the rows
    wait for keeps its own share, so it is drained and the rows go out."""
    from rtloop.record import csvfiles

    monkeypatch.setattr(csvfiles, "MAX_PENDING_VALUES", 2000)
    hour_ns, ms_ns = 3_600_000_000_000, 1_000_000
    writer = SignalsCsv(tmp_path / "signals.csv", [SignalRef("slow", "u", 0, 1), SignalRef("fast", "y", 0, 2)],
                        {"slow": hour_ns, "fast": ms_ns}, {"slow": 1, "fast": 2})
    assert writer.room("fast") == 500 and writer.room("slow") == 1000  # a share of 1000 values each
    writer.add("fast", np.arange(-1, 499), np.ones((500, 2)))  # the slow task has delivered nothing yet
    writer.flush()
    assert writer.room("fast") == 0 and writer.room("slow") == 1000
    writer.add("slow", np.array([-1, 0]), np.zeros((2, 2)))  # y then u of its tick 0
    times, _ = writer.flush()
    assert len(times) == 500 and writer.room("fast") == 500
    writer.close()
