"""Comparing a replay with its run, row by row and bit for bit, and explaining the first difference:
which task and cycle, the values on both sides, the inputs of that cycle (a second, short replay
captures them) and what the run's logs say of it."""

from __future__ import annotations

import csv
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from rtloop.app.builder import App
from rtloop.record.csvfiles import column_names
from rtloop.runtime.replay.logs import CycleRecord, whole_lines
from rtloop.runtime.replay.timeline import RunTimeline
from rtloop.runtime.simulate import PortWrites, simulate
from rtloop.seconds import ns_from_seconds

DIVERGENCE_DIR = "divergence"
"""Inside the replay's folder: the short second replay that captures the inputs of the first divergence."""


@dataclass(frozen=True)
class Divergence:
    """The first place where the replay differs from the run."""

    t_s: float
    """Time of the first ``signals.csv`` row that differs."""
    task: str
    """The task whose cycle produced the first differing value."""
    cycle: int
    """That cycle (its outputs hold from ``t_s`` if a ``y`` differs; its inputs are read at ``t_s`` if a ``u`` does)."""
    signals: tuple[tuple[str, str, str], ...]
    """(column, value in the run, value in the replay) of every column of that row that differs."""
    inputs: tuple[float, ...] | None = None
    """The task's ``u`` as the replay read it at that cycle (None: not captured)."""
    run_log: tuple[str, ...] = ()
    """What the run's logs say of that cycle: stale reads, port values taken, skips, lateness."""
    changed_files: tuple[str, ...] = ()
    """Files of the app that changed since the run (the replay ran today's)."""

    def describe(self) -> str:
        lines = [f"first difference at t = {self.t_s!r} s: task {self.task!r}, cycle {self.cycle}"]
        lines += [f"  {name}: run {run} != replay {replayed}" for name, run, replayed in self.signals]
        if self.inputs is not None:
            lines.append(f"  inputs of that cycle in the replay: u = {list(self.inputs)!r}")
        lines += [f"  run log: {entry}" for entry in self.run_log]
        if self.changed_files:
            lines.append(f"  the replay ran today's files, and {'; '.join(self.changed_files)}: "
                         "the difference may well come from that change")
        elif not self.run_log:
            lines.append("  the run logged no fault at that cycle: a model that is not deterministic (the clock, "
                         "tick.start_ns, random numbers) or an input that entered unlogged")
        return "\n".join(lines)


def column_owners(app: App) -> list[tuple[str, str]]:
    """(task, side) of each signals.csv column, in order."""
    owners: list[tuple[str, str]] = []
    for ref in app.recorded:
        runnable = app.tasks[ref.task].runnable
        owners += [(ref.task, ref.side)] * len(column_names(ref, runnable.input_names, runnable.output_names))
    return owners


@dataclass
class LostCells:
    """Cells of the run's signals.csv that are empty: values the run lost (its record queue was full)."""

    rows: int = 0
    first_s: float = 0.0
    last_s: float = 0.0
    columns: set[str] = field(default_factory=set)

    def add(self, t_s: float, columns: list[str]) -> None:
        self.first_s = t_s if not self.rows else self.first_s
        self.rows, self.last_s = self.rows + 1, t_s
        self.columns.update(columns)

    def describe(self, counts: dict[str, int]) -> str:
        by_task = ", ".join(f"{task} {count}" for task, count in counts.items()) or "not counted"
        return (f"signals.csv: {self.rows} rows from t = {self.first_s!r} s to {self.last_s!r} s hold cells the run "
                f"lost ({', '.join(sorted(self.columns))}; recording.lost.signal_rows: {by_task}): those cells "
                "are not compared")


def compare_replay(run_csv: Path, replay_csv: Path, app: App, until_ns: int | None = None,
                   from_ns: int = 0, lost: LostCells | None = None,
                   cut: list[str] | None = None) -> tuple[int, int, Divergence | None]:
    """(rows in the run, rows equal from the first, the first divergence) from ``from_ns`` up to
    ``until_ns`` (None: the end). An empty cell of the run is a value it lost: not compared, kept
    in ``lost``; a last row cut short is left out, and said in ``cut``."""
    cut = [] if cut is None else cut
    with open(run_csv, newline="") as a, open(replay_csv, newline="") as b:
        run_rows, replay_rows = list(csv.reader(whole_lines(a, run_csv.name, cut))), list(csv.reader(b))
    if not run_rows:
        return 0, 0, None
    header, rows = run_rows[0], run_rows[1:]
    rows = [row for row in rows if from_ns <= ns_from_seconds(row[0]) and (
        until_ns is None or ns_from_seconds(row[0]) < until_ns)]
    replay_rows = replay_rows[:1] + [row for row in replay_rows[1:] if ns_from_seconds(row[0]) >= from_ns]
    if replay_rows[:1] != [header]:
        got = replay_rows[0] if replay_rows else []
        return len(rows), 0, Divergence(0.0, "", 0, (("columns", ",".join(header), ",".join(got)),))
    owners = column_owners(app)
    periods = {name: task.config.period_ns for name, task in app.tasks.items()}
    lost = LostCells() if lost is None else lost
    for index, run_row in enumerate(rows):
        replay_row = replay_rows[index + 1] if index + 1 < len(replay_rows) else None
        if replay_row == run_row:
            continue
        t_ns = ns_from_seconds(run_row[0])
        if replay_row is None or replay_row[0] != run_row[0]:
            other = "none" if replay_row is None else f"t = {replay_row[0]}"
            return len(rows), index, Divergence(float(run_row[0]), "", 0, (("row", f"t = {run_row[0]}", other),))
        empty = [i for i in range(1, len(header)) if run_row[i] == ""]
        if empty:
            lost.add(float(run_row[0]), [header[i] for i in empty])
        differing = [(header[i], run_row[i], replay_row[i]) for i in range(1, len(header))
                     if run_row[i] != replay_row[i] and run_row[i] != ""]
        if not differing:
            continue
        # the earliest cycle behind a differing column: a y holds from (k+1)·P, a u was read at k·P
        causes = []
        for i in range(1, len(header)):
            if run_row[i] != replay_row[i] and run_row[i] != "":
                task, side = owners[i - 1]
                cycle = t_ns // periods[task] - (1 if side == "y" else 0)
                causes.append((cycle * periods[task], task, cycle))
        _, task, cycle = min(causes)
        return len(rows), index, Divergence(float(run_row[0]), task, cycle, tuple(differing))
    return len(rows), len(rows), None


def run_log_of(task: str, cycle: int, timeline: RunTimeline, writes: PortWrites,
                records: list[CycleRecord], period_ns: int) -> tuple[str, ...]:
    entries = []
    by_cycle = {record.cycle: (i, record) for i, record in enumerate(records)}
    if cycle in by_cycle:
        i, record = by_cycle[cycle]
        if i and records[i - 1].cycle != cycle - 1:
            entries.append(f"it followed skipped releases (cycles {records[i - 1].cycle + 1}..{cycle - 1})")
        if record.end_ns > record.release_ns + period_ns:
            entries.append(f"it ended {(record.end_ns - record.release_ns) / 1e6:.3f} ms after its release "
                           f"(period {period_ns / 1e6:g} ms)")
    else:
        entries.append("the run has no timing record of it")
    for writer, stamp in timeline.reads.get((task, cycle), ()):
        got = "no sample at all" if stamp is None else f"the sample stamped {stamp / 1e9!r} s"
        entries.append(f"stale read of {writer}: got {got}")
    for port, values in writes.get((task, cycle), ()):
        entries.append(f"took {values!r} from port {port!r}")
    return tuple(entries)


def explain(divergence: Divergence, again: RunTimeline, out: Path, writes: PortWrites,
             records: dict[str, list[CycleRecord]], periods: dict[str, int]) -> Divergence:
    """Add the inputs of the diverging cycle: replay again (a fresh app) up to it, keeping its ``u``."""
    task, cycle = divergence.task, divergence.cycle
    period_ns = periods[task]
    again.capture.add((task, cycle))
    scratch = out / DIVERGENCE_DIR
    try:
        simulate(again.app, (cycle + 1) * period_ns / 1e9, scratch, port_writes=writes, timeline=again, force=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    inputs = again.captured.get((task, cycle))
    log = run_log_of(task, cycle, again, writes, records.get(task, []), period_ns)
    return Divergence(divergence.t_s, task, cycle, divergence.signals,
                      None if inputs is None else tuple(inputs.tolist()), log)
