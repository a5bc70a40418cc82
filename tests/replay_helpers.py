"""Test helpers about replays that no command needs: an app to replay, where a run stops equalling
its plain simulation, and how far two signals.csv agree."""

from __future__ import annotations

import csv
from pathlib import Path

from rtloop import App, Runnable
from rtloop.runtime.replay.logs import read_summary, read_timing

PERIOD_NS = 1_000_000


def pi_loop_app(name: str, plant: Runnable | None = None) -> App:
    """A PI controller (1 ms) closing the loop round a plant (2 ms; an integrator unless given), a
    live setpoint port into the controller, both tasks' outputs recorded: multi-rate, fed from outside."""
    from rt_test_runnables import Integrator, PiController

    app = App(name)
    controller = app.add_task("controller", PiController(2), period_ns=PERIOD_NS)
    plant_task = app.add_task("plant", plant or Integrator(2), period_ns=2 * PERIOD_NS)
    app.connect(plant_task.y, controller.u[0:2])
    app.connect(controller.y, plant_task.u)
    app.port("setpoint", to=controller.u[2:4])
    app.record(plant_task.y, controller.y)
    return app


def first_miss_s(run_dir: Path) -> float | None:
    """Release time (since T0) of the run's first cycle that ended after its deadline or followed a skip,
    or of the cycle before the first one whose device read stale values (a frame that came late): up
    to there a run equals its plain simulation (the logical timeline); its replay goes further."""
    summary = read_summary(run_dir)
    periods = {name: task["period_ns"] for name, task in summary["tasks"].items()}
    cut: list[str] = []
    records, _t0_ns = read_timing(run_dir, periods, cut)
    first: int | None = None
    for task, run in records.items():
        previous = -1
        for record in run:
            skipped = record.cycle != previous + 1
            previous = record.cycle
            if record.end_ns > record.release_ns + periods[task] or skipped:
                at = record.release_ns - (periods[task] if skipped else 0)
                first = at if first is None else min(first, at)
    for device in (summary.get("devices") or {}).values():
        stale = device.get("first_stale_cycles") or []
        if stale and device.get("task") in periods:  # its readings at that release were old already
            at = (stale[0] - 1) * periods[device["task"]]
            first = at if first is None else min(first, at)
    return None if first is None else first / 1e9


def compare_signals(run_csv: Path, other_csv: Path, until_s: float | None) -> tuple[int, float | None]:
    """(rows equal from the first, time of the first that differs or None) of two signals.csv, up to ``until_s``."""
    with open(run_csv, newline="") as a, open(other_csv, newline="") as b:
        run_rows, other_rows = list(csv.reader(a)), list(csv.reader(b))
    if run_rows[:1] != other_rows[:1]:
        return 0, 0.0
    compared = 0
    for run_row, other_row in zip(run_rows[1:], other_rows[1:], strict=False):
        t = float(run_row[0])
        if until_s is not None and t > until_s:  # values at the miss's release were computed in time
            break
        if run_row != other_row:
            return compared, t
        compared += 1
    return compared, None
