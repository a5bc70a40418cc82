"""A run's real timeline, followed by the replay: the cycles each task ran (gaps where it skipped
releases), the stale samples it read, and where the files cannot be the whole timeline (records
lost, a ``--keep`` window and the snapshots it starts from)."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.errors import AppError
from rtloop.runtime.replay.logs import CycleRecord
from rtloop.runtime.simulate import LetTimeline
from rtloop.runtime.snapshot import SNAPSHOTS_DIR, TaskSnapshot, read_snapshots, restore_state


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
        guards = task.wiring.guards  # a guarded input holds what its guard let through last: its rate limit goes on
        guards.last[:] = task.u[guards.indices]  # from there (in place: the C core holds this vector)
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

    def read_inputs(self, task: str, cycle: int, release_ns: int, io: Any, wiring: Any) -> None:
        late = self.reads.get((task, cycle))
        instead: dict[int, np.ndarray | None] | None = None
        if late is not None:  # the run read these samples in place of LET's: so does the replay
            instead = {}
            links = {link.writer: index for index, link in enumerate(wiring.links)}
            for writer, stamp_ns in late:
                sample = None if stamp_ns is None else self._take(writer, stamp_ns)
                if stamp_ns is not None and sample is None:
                    self.problems.append((cycle * self.periods_ns[task], (
                        f"{task} cycle {cycle} read {writer}'s sample stamped {stamp_ns} ns, which the "
                        f"replayed {writer} never published (its timing record is missing)")))
                    continue
                link = wiring.links[links[writer]]
                instead[links[writer]] = None if sample is None else sample[link.first : link.first + len(link.scratch)]
        io.read_inputs(release_ns, instead)  # a connection's guard acts on what the run read, as it did in the run
        if (task, cycle) in self.capture:
            self.captured[(task, cycle)] = wiring.u.copy()

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
