"""``rtloop simulate`` shows its progress as a run does: ``summary.json`` is rewritten while the
simulation goes on (``"running": true``, ``stopped_by: "running"``, the logical time reached),
atomically, and the final one says how it ended; ``started`` is when it started, not when it ended."""

from __future__ import annotations

import datetime as dt
import json
import time
from pathlib import Path

import rtloop
from rtloop import App, Runnable
from rtloop.runtime.session import Limits

PERIOD_NS = 1_000_000
PEEK_CYCLE = 50


class PeekSummary(Runnable):
    """At one cycle, reads the simulation's own summary.json: y = [found, running, elapsed_s, wall time]."""

    n_inputs, n_outputs = 0, 4

    def __init__(self, summary_path: str, at_cycle: int) -> None:
        self.summary_path, self.at_cycle = summary_path, at_cycle

    def step(self, u, y) -> None:
        if self.tick.cycle != self.at_cycle:
            return
        y[3] = time.time()
        try:
            summary = json.loads(Path(self.summary_path).read_text())
        except FileNotFoundError:
            return
        y[0] = 1.0
        y[1] = float(summary["running"] is True and summary["stopped_by"] == "running")
        y[2] = summary["elapsed_s"]


def _simulate(tmp_path: Path, interval_s: float) -> tuple[rtloop.RunData, dict]:
    out = tmp_path / "out"
    app = App("simprogress")
    peek = app.add_task("peek", PeekSummary(str(out / "summary.json"), PEEK_CYCLE), period_ns=PERIOD_NS)
    app.record(peek.y)
    rtloop.simulate(app, 0.1, out, limits=Limits(summary_interval_s=interval_s))
    return rtloop.load(out), json.loads((out / "summary.json").read_text())


def _at_the_end(run: rtloop.RunData, index: int) -> float:
    return float(run.signals[f"peek.y[{index}]"][-1])


def test_summary_json_shows_a_simulation_in_progress(tmp_path: Path) -> None:
    run, final = _simulate(tmp_path, interval_s=0.0)  # due at every step: no wall-clock race
    assert _at_the_end(run, 0) == 1.0, "no summary.json while the simulation ran"
    assert _at_the_end(run, 1) == 1.0, "the summary during the simulation did not say it was running"
    assert 0 < _at_the_end(run, 2) <= PEEK_CYCLE * PERIOD_NS / 1e9  # the logical time reached by then
    assert final["running"] is False and final["stopped_by"] == "duration" and final["mode"] == "simulate"
    assert final["tasks"]["peek"]["cycles"] == 100
    started_s = dt.datetime.fromisoformat(final["started"]).timestamp()
    assert started_s <= _at_the_end(run, 3)  # the start, not the end of the simulation
    assert not list((tmp_path / "out").glob(".summary.json.tmp"))


def test_a_short_simulation_writes_no_summary_before_its_end(tmp_path: Path) -> None:
    run, final = _simulate(tmp_path, interval_s=3600.0)
    assert _at_the_end(run, 0) == 0.0  # written at the interval, not at every step
    assert final["running"] is False and final["stopped_by"] == "duration"
