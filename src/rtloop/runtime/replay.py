"""Replay: re-simulate a run with what entered it from outside, at the cycles it took effect.

A run writes ``inputs.csv`` (every new value a task took from a live input port: CLI,
Python client, ROS 2 bridge) and ``replay.json`` (the app file and profile feeds).
:func:`replay` rebuilds the app, simulates it with those values written to their
ports just before the releases that took them, and compares its ``signals.csv`` with
the run's: under logical execution time they agree bit for bit up to the run's first
deadline miss (after a miss, the run itself departed from the logical timeline).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

from rtloop.app.builder import App
from rtloop.errors import AppError
from rtloop.record.csvfiles import read_inputs_csv
from rtloop.runtime.simulate import PortWrites, simulate


@dataclass(frozen=True)
class ReplayResult:
    """How the replay compares with the run."""

    rows_compared: int
    """signals.csv rows compared (those before the run's first miss)."""
    first_difference_s: float | None
    """Time of the first row that differs, or None if every compared row is equal."""
    first_miss_s: float | None
    """Release time of the run's first deadline miss or skipped release (None: none)."""

    @property
    def equal(self) -> bool:
        return self.first_difference_s is None


def load_replay_app(run_dir: Path) -> tuple[App, float]:
    """The app of a run (from replay.json), with its feeds, and the run's duration."""
    from rtloop.app.appfile import load_app

    info_path = run_dir / "replay.json"
    if not info_path.is_file():
        raise AppError(f"{run_dir}: no replay.json; is it the output folder of `rtloop run`?")
    info = json.loads(info_path.read_text())
    if info.get("source", "<python>") == "<python>":
        raise AppError(f"{run_dir}: the app was built in Python; call rtloop.runtime.replay.replay(app, ...)")
    app = load_app(info["source"])
    for port, feed in info.get("feeds", {}).items():
        app.feed(port, feed)
    duration_s = info.get("duration_s")
    summary_path = run_dir / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    if (summary.get("recording") or {}).get("keep_s") is not None:
        raise AppError(f"{run_dir}: recorded with --keep, so signals.csv holds a window, not the run from t = 0; "
                       "replay needs a run recorded whole (--duration without --keep)")
    if duration_s is None:  # a run until stopped: replay as long as it ran
        duration_s = summary.get("elapsed_s") or 0.0
        if not duration_s:
            raise AppError(f"{run_dir}: the run had no --duration and its summary.json does not say how long it ran")
    return app, float(duration_s)


def port_writes(run_dir: Path) -> PortWrites:
    path = run_dir / "inputs.csv"
    writes: PortWrites = {}
    if not path.exists():
        return writes
    try:
        rows = read_inputs_csv(path)
    except ValueError as error:
        raise AppError(str(error)) from None
    for task, cycle, port, values in rows:
        writes.setdefault((task, cycle), []).append((port, values))
    return writes


def first_miss_s(run_dir: Path) -> float | None:
    """Release time (since T0) of the first cycle that ended after its deadline or followed a skip."""
    summary = json.loads((run_dir / "summary.json").read_text())
    periods = {name: task["period_ns"] for name, task in summary["tasks"].items()}
    first: int | None = None
    previous: dict[str, int] = {}
    t0: int | None = None
    rows = []
    with open(run_dir / "timing.csv", newline="") as file:
        for row in csv.DictReader(file):
            rows.append((row["task"], int(row["cycle"]), int(row["release_ns"]), int(row["end_ns"])))
            t0 = int(row["release_ns"]) if t0 is None else min(t0, int(row["release_ns"]))
    for task, cycle, release, end in rows:
        period = periods[task]
        late = end > release + period
        skipped = cycle != previous.get(task, -1) + 1
        previous[task] = cycle
        if late or skipped:
            at = release - (t0 or 0) - (period if skipped else 0)
            first = at if first is None else min(first, at)
    return None if first is None else first / 1e9


def compare_signals(run_csv: Path, replay_csv: Path, until_s: float | None) -> tuple[int, float | None]:
    with open(run_csv, newline="") as a, open(replay_csv, newline="") as b:
        run_rows, replay_rows = list(csv.reader(a)), list(csv.reader(b))
    if run_rows[:1] != replay_rows[:1]:
        return 0, 0.0
    compared = 0
    for run_row, replay_row in zip(run_rows[1:], replay_rows[1:], strict=False):
        t = float(run_row[0])
        if until_s is not None and t > until_s:  # values at the miss's release were computed in time
            break
        if run_row != replay_row:
            return compared, t
        compared += 1
    return compared, None


def replay(run_dir: str | Path, out: str | Path, app: App | None = None) -> ReplayResult:
    """Re-simulate the run in ``run_dir`` into ``out``; compare the signals up to its first miss."""
    run_dir, out = Path(run_dir), Path(out)
    if app is None:
        app, duration_s = load_replay_app(run_dir)
    else:
        duration_s = float(json.loads((run_dir / "replay.json").read_text())["duration_s"] or 0.0) or 1e8
    summary = json.loads((run_dir / "summary.json").read_text())
    cycles = max((t.get("cycles", 0) + t.get("overruns", 0)) * t["period_ns"] for t in summary["tasks"].values())
    duration_s = min(duration_s, cycles / 1e9) if cycles else duration_s  # a run stopped early
    simulate(app, duration_s, out, port_writes=port_writes(run_dir))
    miss_s = first_miss_s(run_dir)
    if not (run_dir / "signals.csv").exists():
        return ReplayResult(0, None, miss_s)
    compared, difference = compare_signals(run_dir / "signals.csv", out / "signals.csv", miss_s)
    return ReplayResult(compared, difference, miss_s)
