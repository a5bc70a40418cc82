"""Lifecycle bugs around the real-time loop (issue 29): each test here failed before its fix."""

from __future__ import annotations

import csv
import os
import re
import signal
import threading
from pathlib import Path

import pytest

import rtloop
from rt_test_runnables import Counter, FailsWithSlowPostrun
from rtloop import App
from rtloop.errors import TaskFailed
from rtloop.runtime.session import Limits

PERIOD_NS = 10_000_000
FAIL_CYCLE = 20


def _releases_of(out: Path, task: str) -> list[int]:
    with open(out / "timing.csv", newline="") as file:
        return [int(row["release_ns"]) for row in csv.DictReader(file) if row["task"] == task]


def _failed_at_ns(failure: TaskFailed) -> int:
    match = re.search(r"failed at (\d+) ns", failure.reason)
    assert match, failure.reason
    return int(match.group(1))


@pytest.mark.parametrize("postrun_s", [2.5, None], ids=["slow-postrun", "hung-postrun"])
def test_a_failed_task_stops_the_healthy_one_within_two_of_its_periods(tmp_path: Path, postrun_s: float | None) -> None:
    """Task A fails at cycle 20 and then spends 2.5 s in postrun (or hangs there, in a run without a
    duration): task B must not go on meanwhile (its devices would be driven from A's last outputs)."""
    app = App(f"failstop_{os.getpid()}_{'hung' if postrun_s is None else 'slow'}")
    app.add_task("a", FailsWithSlowPostrun(FAIL_CYCLE, postrun_s), period_ns=PERIOD_NS)
    app.add_task("b", Counter(), period_ns=PERIOD_NS)
    duration_s = None if postrun_s is None else 10.0
    # Before the fix a hung postrun kept the app running for ever: a Ctrl-C after 20 s ends the test.
    rescue = threading.Timer(20.0, os.kill, (os.getpid(), signal.SIGINT))
    rescue.start()
    try:
        with pytest.raises(TaskFailed) as failed:
            rtloop.run(app, duration_s, tmp_path / "out", limits=Limits(stop_grace_s=1.0))
    finally:
        rescue.cancel()
    assert failed.value.task == "a" and failed.value.phase == "step"
    failed_at_ns = _failed_at_ns(failed.value)
    late = [release for release in _releases_of(tmp_path / "out", "b") if release > failed_at_ns + 2 * PERIOD_NS]
    assert late == [], f"b ran {len(late)} cycles released more than 2 periods after a's failure"
