"""Replay: re-simulate a whole run offline, its timing faults included, and compare it bit for bit.

A run leaves what its tasks really did beside its signals: ``timing.csv`` (every cycle
run, so the releases skipped after an overrun show as gaps), ``reads.csv`` (every read of
a connection that got an older sample than logical execution time promised: a stale
read), ``inputs.csv`` (every value taken from a live port, with the cycle that took it)
and ``replay.json`` (the app file and profile feeds). :func:`replay` rebuilds the app and
simulates it along that real timeline (:class:`RunTimeline`): each task runs the cycles
it ran, skips the ones it skipped, and reads the samples it read. Then the replay's
``signals.csv`` equals the run's bit for bit over the whole run, however many misses it
had; :func:`compare_replay` checks every row, and a difference comes back as a
:class:`Divergence` (first cycle, task, signals on both sides, the inputs of that cycle).

Where the replay cannot follow the run (a timing record the run lost, early cycles a
``--keep`` run did not keep), :attr:`ReplayResult.cannot` says why and from where, and
the result is not called equal. Whatever else the run's summary says it lost on the way
(``recording.lost``: signal rows, port values it took but did not log; stale reads its read
log dropped; a recording that stopped) is named in :attr:`ReplayResult.lost`: the replay
compares what the files hold, leaves out the cells the run lost, and never calls the
result equal over data it does not have.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import shutil
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.app.sources import changes_since
from rtloop.errors import AppError
from rtloop.record.csvfiles import column_names, read_inputs_csv, read_reads_csv
from rtloop.record.disk_room import check_room
from rtloop.record.jsonfile import parse_json
from rtloop.runtime.session import UNFINISHED_FOLDER, check_out_dir
from rtloop.runtime.simulate import LetTimeline, PortWrites, simulate
from rtloop.runtime.snapshot import SNAPSHOTS_DIR, TaskSnapshot, read_snapshots, restore_state

DIVERGENCE_DIR = "divergence"
"""Inside the replay's folder: the short second replay that captures the inputs of the first divergence."""


@dataclass(frozen=True)
class CycleRecord:
    """One cycle of a task as the run's ``timing.csv`` holds it (times in ns since T0)."""

    cycle: int
    release_ns: int
    start_ns: int
    end_ns: int


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


@dataclass(frozen=True)
class ReplayResult:
    """How the replay compares with the run."""

    rows_in_run: int
    """Rows of the run's signals.csv."""
    rows_compared: int
    """Rows compared and found equal, from the first."""
    divergence: Divergence | None
    """The first difference (None: none among the rows compared)."""
    cannot: str | None = None
    """Why the replay cannot reproduce the run from some point on, and where (None: it can)."""
    skipped_releases: int = 0
    """Releases the run skipped (overruns), followed by the replay."""
    stale_reads: int = 0
    """Stale reads of the run followed by the replay (the samples it actually read)."""
    port_inputs: int = 0
    """Port values the run took, fed back at the cycles that took them."""
    notes: tuple[str, ...] = field(default=())
    from_s: float = 0.0
    """Where the replay starts: 0, or the start of a ``--keep`` run's kept window (a snapshot)."""
    lost: tuple[str, ...] = field(default=())
    """What the run lost on the way (its summary's ``recording``), each with where: the replay
    cannot check it, so the result is never equal while this is not empty."""

    @property
    def equal(self) -> bool:
        """Every row of the run compared, and equal bit for bit (never True when nothing was compared,
        nor when the run lost part of what it did)."""
        return (self.cannot is None and self.divergence is None and not self.lost and self.rows_in_run > 0
                and self.rows_compared == self.rows_in_run)

    @property
    def first_difference_s(self) -> float | None:
        return None if self.divergence is None else self.divergence.t_s


# --- the run's logs --------------------------------------------------------------------------------


def read_summary(run_dir: Path) -> dict[str, Any]:
    path = run_dir / "summary.json"
    if not path.is_file():
        raise AppError(f"{run_dir}: no summary.json; is it the output folder of `rtloop run`?")
    try:
        summary: dict[str, Any] = parse_json(path.read_text())
        return summary
    except ValueError as error:
        raise AppError(f"{path}: not JSON ({error})") from None


def load_replay_app(run_dir: Path) -> tuple[App, float | None]:
    """The app of a run (from replay.json), with its feeds, and the run's ``--duration`` (None: none)."""
    from rtloop.app.appfile import load_app

    info_path = run_dir / "replay.json"
    if not info_path.is_file():
        raise AppError(f"{run_dir}: no replay.json; is it the output folder of `rtloop run`?")
    try:
        info = parse_json(info_path.read_text())
    except (OSError, ValueError) as error:
        raise AppError(f"{info_path}: not readable JSON ({error})") from None
    if not isinstance(info, dict):
        raise AppError(f"{info_path}: not a replay.json (expected a JSON object)")
    if info.get("source", "<python>") == "<python>":
        raise AppError(f"{run_dir}: the app was built in Python; call rtloop.runtime.replay.replay(run_dir, out, app)")
    app = load_app(info["source"])
    for port, feed in info.get("feeds", {}).items():
        app.feed(port, feed)
    duration_s = info.get("duration_s")
    return app, None if duration_s is None else float(duration_s)


def play_back_devices(app: App, run_dir: Path) -> None:
    """Put in each device's place what it read in the run: the task inputs it fed, as recorded
    (a device's readings are always recorded, in the row of the release that read them)."""
    from rtloop.io.twin import PlaybackTwin

    with open(run_dir / "signals.csv", newline="") as file:
        rows = list(csv.reader(file))
    header = {name: index for index, name in enumerate(rows[0])} if rows else {}
    for spec in app.devices.values():
        device, owner = spec.device, app.tasks[spec.task]
        period_ns = owner.config.period_ns
        readings: dict[int, np.ndarray] = {}
        for link in app.device_links:
            if link.source.task != spec.name:
                continue
            names = column_names(link.target, owner.runnable.input_names, owner.runnable.output_names)
            missing = [name for name in names if name not in header]
            if missing:
                raise AppError(f"{run_dir}: signals.csv has no column {missing[0]} (what device {spec.name!r} "
                               "read): a run of an older rtloop; it cannot be replayed without the device")
            columns = [header[name] for name in names]
            for row in rows[1:]:
                t_ns = round(float(row[0]) * 1e9)
                cycle = t_ns // period_ns  # inputs are recorded at the release that read them (outputs at t + P)
                if cycle < 0 or t_ns % period_ns or any(row[c] == "" for c in columns):
                    continue
                values = readings.setdefault(cycle, np.zeros(device.n_outputs))
                values[link.source.slice] = [float(row[c]) for c in columns]
        spec.twin = PlaybackTwin(spec.name, device.n_inputs, device.n_outputs, readings)


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


def whole_lines(file: Iterable[str], name: str, cut: list[str]) -> Iterator[str]:
    """The lines of a file the recorder wrote, without a last line cut short (a full disk or a
    kill -9 stopped the writer in the middle of it): where it was cut is added to ``cut``."""
    for number, line in enumerate(file, start=1):
        if not line.endswith("\n"):
            cut.append(f"{name} line {number}: its last line is cut short (the recording stopped there); left out")
            return
        yield line


def unfinished(run_dir: Path, summary: dict[str, Any] | None = None) -> str:
    """Why a run's files were never joined (a run killed, or still running), '' if they were
    (``summary``: its summary.json, when it has one)."""
    if (run_dir / UNFINISHED_FOLDER).is_dir():
        return (f"{run_dir}: the run never finished (killed, or still running): its recording is in "
                f"{UNFINISHED_FOLDER}/, never joined into timing.csv and signals.csv, so it cannot be replayed "
                "(rtloop.load reads it)")
    if summary is not None and summary.get("running"):
        return (f"{run_dir}: the run never finished (summary.json still says running: killed, or still "
                "running): its timing.csv is not whole, so it cannot be replayed")
    return ""


def read_timing(run_dir: Path, periods_ns: dict[str, int],
                cut: list[str] | None = None) -> tuple[dict[str, list[CycleRecord]], int]:
    """Each task's cycles from timing.csv (times since T0), in order, and T0 (ns, the run's clock).

    A last line cut short is left out, and said in ``cut``."""
    path = run_dir / "timing.csv"
    if not path.is_file():
        raise AppError(f"{run_dir}: no timing.csv: the run's timeline is unknown")
    cycles: dict[str, list[CycleRecord]] = {name: [] for name in periods_ns}
    t0_ns: int | None = None
    with open(path, newline="") as file:
        for number, row in enumerate(csv.DictReader(whole_lines(file, path.name, [] if cut is None else cut)),
                                     start=2):
            try:
                task, cycle = row["task"], int(row["cycle"])
                release, start, end = int(row["release_ns"]), int(row["start_ns"]), int(row["end_ns"])
                period = periods_ns[task]
            except (KeyError, TypeError, ValueError):
                raise AppError(f"{path}:{number}: expected task,cycle,release_ns,start_ns,end_ns of a task "
                               f"of the app ({', '.join(periods_ns)})") from None
            t0_ns = release - cycle * period if t0_ns is None else t0_ns
            if release - cycle * period != t0_ns:
                raise AppError(f"{path}:{number}: release {release} of {task} cycle {cycle} is off its timeline")
            cycles[task].append(CycleRecord(cycle, release - t0_ns, start - t0_ns, end - t0_ns))
    for records in cycles.values():
        records.sort(key=lambda record: record.cycle)
    return cycles, t0_ns or 0


# --- the run's timeline, followed ------------------------------------------------------------------


class RunTimeline(LetTimeline):
    """A run's real timeline for :func:`~rtloop.runtime.simulate.simulate`: its cycles and its reads.

    Each task runs exactly the cycles ``timing.csv`` holds. At a cycle ``reads.csv`` lists,
    the task first reads as LET says, then each late connection is given the sample the run
    got instead: the writer's outputs published with that stamp (kept when the replayed
    writer published them, and only those a logged read needs), or, when the run found no
    sample, the values its inputs held before the read.
    """

    def __init__(self, app: App, cycles: dict[str, list[int]],
                 reads: list[tuple[str, int, str, int | None, int]],
                 resume: dict[str, TaskSnapshot] | None = None) -> None:
        self.app = app
        self.resume = resume or {}
        """Per task, the snapshot a ``--keep`` window starts from (none: the task starts from prerun)."""
        self.periods_ns = {name: task.config.period_ns for name, task in app.tasks.items()}
        self.cycles = cycles
        self._next: dict[str, dict[int, int]] = {
            name: dict(pairwise(run)) for name, run in cycles.items()}
        self.spans: dict[tuple[str, str], list[tuple[slice, slice]]] = {}
        for connection in app.connections:
            key = (connection.target.task, connection.source.task)
            self.spans.setdefault(key, []).append((connection.source.slice, connection.target.slice))
        self.reads: dict[tuple[str, int], list[tuple[str, int | None]]] = {}
        self.uses: dict[tuple[str, int], int] = {}
        for task, cycle, writer, stamp_ns, _due_ns in reads:
            if (task, writer) not in self.spans:
                raise AppError(f"reads.csv: {task} has no connection from {writer}")
            self.reads.setdefault((task, cycle), []).append((writer, stamp_ns))
            if stamp_ns is not None:
                self.uses[(writer, stamp_ns)] = self.uses.get((writer, stamp_ns), 0) + 1
        self.kept: dict[tuple[str, int], np.ndarray] = {}
        self.problems: list[tuple[int, str]] = []
        """(release since T0, what could not be followed) — a sample the replayed writer never published."""
        self.captured: dict[tuple[str, int], np.ndarray] = {}
        self.capture: set[tuple[str, int]] = set()
        """(task, cycle) whose inputs to keep in :attr:`captured` (a divergence report)."""

    def start(self, task: Any, layout: Any, t0_ns: int) -> None:
        """From a snapshot: the runnable's state, ``u``, ``y`` and the live ports' values as they stood."""
        snapshot = self.resume.get(task.name)
        if snapshot is None:
            task.wiring.stamp_initial(t0_ns)
            return
        assert snapshot.state is not None
        restore_state(task.runnable, snapshot.state)
        task.u[:] = snapshot.u
        task.y[:] = task.wiring.initial_y[:] = snapshot.y
        task.wiring.stamp_initial(t0_ns, last_cycle=snapshot.last_cycle, period_ns=task.period_ns)
        for stamp_ns, values in getattr(snapshot, "outputs", ()):  # older samples a late read may still get
            self.published(task.name, stamp_ns // task.period_ns - 1, np.asarray(values, dtype=np.float64))
        self.published(task.name, snapshot.last_cycle, task.y)
        # a profile's row in force and its live nudges are not in u: as they stood after the last release
        task.wiring.resume_profiles(snapshot.last_cycle * task.period_ns, dict(getattr(snapshot, "nudges", ())))
        for name, port in self.app.ports.items():  # a port holds its last value; the task reads it again
            if port.direction == "in" and port.feed is None and port.signal.task == task.name:
                layout.input_ports[name].write(np.asarray(snapshot.u[port.signal.slice], dtype=np.float64))

    def first_cycle(self, task: str) -> int | None:
        run = self.cycles.get(task)
        return run[0] if run else None

    def next_cycle(self, task: str, cycle: int) -> int | None:
        return self._next[task].get(cycle)

    def read_inputs(self, task: str, cycle: int, release_ns: int, io: Any, u: np.ndarray) -> None:
        late = self.reads.get((task, cycle))
        if late is None:
            io.read_inputs(release_ns)
        else:
            before = u.copy()
            io.read_inputs(release_ns)
            for writer, stamp_ns in late:
                sample = None if stamp_ns is None else self._take(writer, stamp_ns)
                if stamp_ns is not None and sample is None:
                    self.problems.append((cycle * self.periods_ns[task], (
                        f"{task} cycle {cycle} read {writer}'s sample stamped {stamp_ns} ns, which the "
                        f"replayed {writer} never published (its timing record is missing)")))
                    continue
                for source, target in self.spans[(task, writer)]:
                    u[target] = before[target] if sample is None else sample[source]
        if (task, cycle) in self.capture:
            self.captured[(task, cycle)] = u.copy()

    def _take(self, writer: str, stamp_ns: int) -> np.ndarray | None:
        key = (writer, stamp_ns)
        sample = self.kept.get(key)
        if sample is not None:
            self.uses[key] -= 1
            if not self.uses[key]:
                del self.kept[key]  # nothing later needs it: the kept samples stay few
        return sample

    def published(self, task: str, cycle: int, y: np.ndarray) -> None:
        key = (task, (cycle + 1) * self.periods_ns[task])
        if key in self.uses:
            self.kept[key] = y.copy()


def check_timeline(cycles: dict[str, list[CycleRecord]], periods_ns: dict[str, int],
                   dropped: dict[str, int], starts: dict[str, int] | None = None) -> tuple[int, str] | None:
    """The first place where ``timing.csv`` cannot be the whole timeline from each task's start
    cycle (``starts``, default 0): (release since T0, why)."""
    first: tuple[int, str] | None = None
    for task, records in cycles.items():
        period = periods_ns[task]
        start = (starts or {}).get(task, 0)
        lost = f" (its timing ring dropped {dropped[task]} records)" if dropped.get(task) else ""
        problem = None
        if records and records[0].cycle != start:
            problem = (start * period, f"timing.csv starts {task} at cycle {records[0].cycle}, not {start}{lost}")
        for before, after in pairwise(records):
            if problem is not None:
                break
            if after.cycle == before.cycle:
                problem = (after.release_ns, f"timing.csv holds {task} cycle {after.cycle} twice")
            elif after.cycle > before.cycle + 1 and before.end_ns <= before.release_ns + period:
                # releases are skipped only after an overrun: these cycles ran, unrecorded
                problem = ((before.cycle + 1) * period,
                           f"timing.csv lacks {task} cycles {before.cycle + 1}..{after.cycle - 1}, which "
                           f"followed a cycle that ended in time{lost}: the replay cannot know what they did")
            elif after.cycle > before.cycle + 1 and dropped.get(task):
                # after an overrun: skipped releases, or records the ring dropped; the files cannot tell
                problem = ((before.cycle + 1) * period,
                           f"timing.csv lacks {task} cycles {before.cycle + 1}..{after.cycle - 1} after an "
                           f"overrun, and the run lost {dropped[task]} of {task}'s timing records "
                           "(recording.lost): skipped releases or lost cycles, the replay cannot tell which")
        if problem is not None and (first is None or problem[0] < first[0]):
            first = problem
    return first


# --- comparing -------------------------------------------------------------------------------------


def _column_owners(app: App) -> list[tuple[str, str]]:
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
    rows = [row for row in rows if from_ns <= round(float(row[0]) * 1e9) and (
        until_ns is None or round(float(row[0]) * 1e9) < until_ns)]
    replay_rows = replay_rows[:1] + [row for row in replay_rows[1:] if round(float(row[0]) * 1e9) >= from_ns]
    if replay_rows[:1] != [header]:
        got = replay_rows[0] if replay_rows else []
        return len(rows), 0, Divergence(0.0, "", 0, (("columns", ",".join(header), ",".join(got)),))
    owners = _column_owners(app)
    periods = {name: task.config.period_ns for name, task in app.tasks.items()}
    lost = LostCells() if lost is None else lost
    for index, run_row in enumerate(rows):
        replay_row = replay_rows[index + 1] if index + 1 < len(replay_rows) else None
        if replay_row == run_row:
            continue
        t_ns = round(float(run_row[0]) * 1e9)
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


def _run_log_of(task: str, cycle: int, timeline: RunTimeline, writes: PortWrites,
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


# --- a run against its plain simulation (the logical timeline) ------------------------------------


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


# --- replay ----------------------------------------------------------------------------------------


def replay(run_dir: str | Path, out: str | Path, app: App | None = None, *, force: bool = False) -> ReplayResult:
    """Re-simulate the run in ``run_dir`` along its real timeline into ``out``; compare every signal row.

    ``out`` may not be ``run_dir`` nor inside it; a folder holding another run needs ``force``.
    A ``--keep`` run is replayed from the earliest point its files hold the rest of the run
    from: t = 0 if they still do, else the start of its kept window (a snapshot of every task).
    """
    run_dir, out = Path(run_dir), Path(out)
    check_out_dir(out, protect=[run_dir])  # before reading anything: refusals come first
    changed = changed_files(run_dir)
    never_finished = unfinished(run_dir)  # a run killed early may not even have a summary.json
    if never_finished:
        raise AppError(never_finished)
    summary = read_summary(run_dir)
    never_finished = unfinished(run_dir, summary)
    if never_finished:
        raise AppError(never_finished)
    if app is None:
        app, _duration_s = load_replay_app(run_dir)
    if app.devices:
        play_back_devices(app, run_dir)
    pristine = copy.deepcopy(app)  # runnables as before any prerun, for a second pass
    recording = summary.get("recording") or {}
    periods = {name: task.config.period_ns for name, task in app.tasks.items()}
    cut: list[str] = []
    records, _t0_ns = read_timing(run_dir, periods, cut)
    tasks = summary.get("tasks") or {}
    lost_timing = recording_losses(recording, run_dir).get("timing_records", {})
    dropped = {name: max(int((tasks.get(name) or {}).get("timing_samples_dropped") or 0), lost_timing.get(name, 0))
               for name in periods}
    try:
        reads = read_reads_csv(run_dir / "reads.csv") if (run_dir / "reads.csv").exists() else []
    except ValueError as error:
        raise AppError(str(error)) from None
    notes = [f"{change}: the replay runs it as it is now" for change in changed]
    notes += [_stale_device_note(name, device) for name, device in (summary.get("devices") or {}).items()
              if device.get("stale_reads")]
    if app.connections and not (run_dir / "reads.csv").exists():
        notes.append("the run has no reads.csv (recorded by an older rtloop): stale reads are not followed")
    resume: dict[str, TaskSnapshot] = {}
    if recording.get("keep_s") is not None and check_timeline(records, periods, dropped) is not None:
        start = window_start(run_dir, records, periods, dropped)
        if isinstance(start, str):
            return ReplayResult(0, 0, None, cannot=start, notes=tuple(notes),
                                lost=tuple(lost_on_the_way(recording, run_dir)))
        resume = start
    starts = {name: snapshot.next_cycle for name, snapshot in resume.items()}
    from_ns = max((s.at_ns for s in resume.values()), default=0)
    records = {name: [r for r in run if r.cycle >= starts.get(name, 0)] for name, run in records.items()}
    reads = [read for read in reads if read[1] >= starts.get(read[0], 0)]
    writes = {key: value for key, value in port_writes(run_dir).items() if key[1] >= starts.get(key[0], 0)}

    cycles = {name: [r.cycle for r in run] for name, run in records.items()}
    followed = RunTimeline(app, cycles, reads, resume)
    last_release_ns = max((run[-1].release_ns + periods[name] for name, run in records.items() if run), default=0)
    if not last_release_ns:
        raise AppError(f"{run_dir}: timing.csv holds no cycle: nothing to replay")
    replayed_s = (last_release_ns - from_ns) / 1e9  # a --keep window: its span, not the run's
    check_room(app, Path(out), replayed_s, what=f"the replay of {replayed_s:.15g} s",
               remedy="replay into an --out with more room")
    simulate(app, last_release_ns / 1e9, out, port_writes=writes, timeline=followed, force=force,
             protect=(run_dir,))
    gap = check_timeline(records, periods, dropped, starts)
    at_end = timing_lost_at_the_end(records, periods, dropped, _run_end_ns(summary, records, periods))
    problems = sorted(followed.problems + ([gap] if gap else []) + at_end)
    recorded_until_ns = None
    if recording.get("stopped"):  # the run went on without its recording: compare up to where every task has it
        recorded_until_ns = min((run[-1].release_ns + periods[name] if run else 0) for name, run in records.items())
        problems = [problem for problem in problems if problem[0] < recorded_until_ns] or [(recorded_until_ns, "")]
    cannot = None
    if problems and problems[0][1]:
        at_ns, why = problems[0]
        cannot = f"from t = {at_ns / 1e9!r} s: {why}"
    skipped = sum(b.cycle - a.cycle - 1 for run in records.values() for a, b in pairwise(run))
    lost = lost_on_the_way(recording, run_dir, recorded_until_ns) + cut
    for task, run in records.items() if not from_ns else ():  # from t = 0 a loss must show in timing.csv
        shown = any(b.cycle != a.cycle + 1 for a, b in pairwise(run)) or any(
            f" of {task}'s timing records" in why for _at, why in at_end)
        if dropped.get(task) and not shown:
            lost.append(f"the run says it lost {dropped[task]} of {task}'s timing records (recording.lost), yet "
                        "timing.csv shows no place they could have been: the replay cannot tell what they were")
    common: dict[str, Any] = {"cannot": cannot, "skipped_releases": skipped, "stale_reads": len(reads),
                              "port_inputs": sum(len(v) for v in writes.values()), "notes": tuple(notes),
                              "from_s": from_ns / 1e9, "lost": tuple(lost)}
    if not (run_dir / "signals.csv").exists():
        return ReplayResult(0, 0, None, **{**common, "cannot": cannot or "the run recorded no signals.csv: "
                                           "nothing to compare"})
    until_ns = problems[0][0] if problems else None
    lost_cells = LostCells()
    rows, equal_rows, divergence = compare_replay(run_dir / "signals.csv", out / "signals.csv", app, until_ns,
                                                  from_ns, lost_cells, cut)
    common["lost"] += tuple(line for line in cut if line not in common["lost"])
    if lost_cells.rows:
        common["lost"] += (lost_cells.describe(recording_losses(recording, run_dir).get("signal_rows", {})),)
    if not rows and common["cannot"] is None:
        common["cannot"] = "the run's signals.csv holds no rows: nothing to compare"
    if divergence is not None and divergence.task:
        again = RunTimeline(pristine, cycles, reads, resume)
        divergence = _explain(divergence, again, out, writes, records, periods)
    if divergence is not None and changed:
        divergence = dataclasses.replace(divergence, changed_files=tuple(changed))
    return ReplayResult(rows, equal_rows, divergence, **common)


def changed_files(run_dir: Path) -> list[str]:
    """The files of the run's app (replay.json's ``files``) whose content is not what the run loaded."""
    try:
        recorded = parse_json((run_dir / "replay.json").read_text()).get("files") or {}
    except (OSError, ValueError, AttributeError):
        return []  # no replay.json, or one from before files were recorded: the loading says what is wrong
    return changes_since({str(path): str(digest) for path, digest in recorded.items()}) if isinstance(
        recorded, dict) else []


def _stale_device_note(name: str, device: dict[str, Any]) -> str:
    """The replay's log line for a device that read stale values in the run (summary.json ``devices``)."""
    count, cycles = int(device.get("stale_cycles") or 0), list(device.get("first_stale_cycles") or [])
    shown = ", ".join(str(cycle) for cycle in cycles[:10]) + (", …" if count > 10 else "")
    return (f"device {name!r} read stale values in {count} cycles ({shown}; the longest lag "
            f"{device.get('longest_lag_cycles')} cycles in a row): played back as the run read them")


def recording_losses(recording: dict[str, Any], run_dir: Path) -> dict[str, dict[str, int]]:
    """summary.json's ``recording.lost`` (per kind, per task, counts > 0): {} where it says nothing."""
    lost = recording.get("lost") or {}
    try:
        return {str(kind): {str(task): int(count) for task, count in counts.items() if int(count) > 0}
                for kind, counts in lost.items()}
    except (AttributeError, TypeError, ValueError):
        raise AppError(f"{run_dir / 'summary.json'}: recording.lost is not counts per kind and task") from None


def _run_end_ns(summary: dict[str, Any], records: dict[str, list[CycleRecord]], periods_ns: dict[str, int]) -> int:
    """When the run's releases ended (since T0): its duration if it ran to it, else its tasks' last records."""
    last = max((run[-1].release_ns + periods_ns[name] for name, run in records.items() if run), default=0)
    duration_s = summary.get("duration_s")
    if summary.get("stopped_by") == "duration" and isinstance(duration_s, int | float) and duration_s > 0:
        return max(last, round(duration_s * 1e9))
    return last


def timing_lost_at_the_end(records: dict[str, list[CycleRecord]], periods_ns: dict[str, int],
                           dropped: dict[str, int], end_ns: int) -> list[tuple[int, str]]:
    """Tasks that lost timing records although timing.csv shows no gap in their cycles, and whose last
    record, which ended in time, came a period or more before the run's end (``end_ns``): the records
    were lost after it, and the replay can follow the task only up to there. (Records lost before a
    ``--keep`` window leave neither mark.)"""
    problems = []
    for task, run in records.items():
        if not dropped.get(task) or not run or any(b.cycle != a.cycle + 1 for a, b in pairwise(run)):
            continue  # nothing lost, nothing to follow, or a gap (check_timeline names it)
        period, last_record = periods_ns[task], run[-1]
        if last_record.end_ns > last_record.release_ns + period or last_record.release_ns + 2 * period > end_ns:
            continue  # an overrun at the end skips what follows; or it ran to the end
        last = last_record.cycle
        problems.append(((last + 1) * periods_ns[task], (
            f"the run lost {dropped[task]} of {task}'s timing records (recording.lost) and timing.csv shows no "
            f"gap in its cycles: they were lost after its last record (cycle {last}), so the replay follows "
            f"{task} only up to there")))
    return problems


def lost_on_the_way(recording: dict[str, Any], run_dir: Path, recorded_until_ns: int | None = None) -> list[str]:
    """What the run's summary says it lost (besides timing records: those cut the timeline) and the
    replay therefore cannot check, each with what it means for the replay."""
    losses = recording_losses(recording, run_dir)
    lost = []
    for task, count in losses.get("inputs", {}).items():
        lost.append(f"the run took {count} values from ports of {task} that it did not log (recording.lost.inputs: "
                    "its input log was full): the replay cannot feed them, and the run does not say when they "
                    "came, so rows may differ from then on")
    for task, count in (recording.get("reads_dropped") or {}).items():
        lost.append(f"the run's read log of {task} dropped {count} stale reads (recording.reads_dropped: ring "
                    "full): the replay reads what logical execution time promised there instead")
    if recording.get("stopped"):
        until = f" (timing.csv holds every task up to t = {recorded_until_ns / 1e9!r} s)" if recorded_until_ns else ""
        lost.append(f"the recording stopped during the run ({recording['stopped']}): its files end there{until}, "
                    "what was recorded is replayed and compared, the rest of the run is not")
    return lost


def window_start(run_dir: Path, records: dict[str, list[CycleRecord]], periods_ns: dict[str, int],
                 dropped: dict[str, int]) -> dict[str, TaskSnapshot] | str:
    """The snapshots of the earliest instant from which the run's files hold every cycle to the end,
    or why there is none."""
    folder = run_dir / SNAPSHOTS_DIR
    found: dict[int, dict[str, TaskSnapshot]] = {}
    for path in sorted(folder.glob("*.pkl")) if folder.is_dir() else []:
        try:
            for snapshot in read_snapshots(path):
                found.setdefault(snapshot.at_ns, {})[snapshot.task] = snapshot
        except (OSError, ValueError, EOFError) as error:
            raise AppError(f"{path}: cannot read task snapshots ({error})") from None
    if not found:
        return ("the run was recorded with --keep and its files no longer hold it from t = 0, but it kept no "
                f"task snapshot ({SNAPSHOTS_DIR}/ is missing or empty): its window cannot be replayed")
    why = ""
    for at_ns in sorted(found):
        snapshots = found[at_ns]
        missing = sorted(set(periods_ns) - set(snapshots))
        lost = [s for s in snapshots.values() if s.state is None]
        if missing:
            why = f"at t = {at_ns / 1e9!r} s no snapshot of {', '.join(missing)}"
            continue
        if lost:
            why = (f"the window from t = {at_ns / 1e9!r} s cannot be replayed: the state of task "
                   f"{lost[0].task!r} could not be saved ({lost[0].reason})")
            continue
        starts = {name: snapshot.next_cycle for name, snapshot in snapshots.items()}
        tail = {name: [r for r in run if r.cycle >= starts[name]] for name, run in records.items()}
        if check_timeline(tail, periods_ns, dropped, starts) is None:
            return snapshots
        why = f"the files do not hold every cycle after the snapshot at t = {at_ns / 1e9!r} s"
    return why


def _explain(divergence: Divergence, again: RunTimeline, out: Path, writes: PortWrites,
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
    log = _run_log_of(task, cycle, again, writes, records.get(task, []), period_ns)
    return Divergence(divergence.t_s, task, cycle, divergence.signals,
                      None if inputs is None else tuple(inputs.tolist()), log)
