"""Task snapshots: a task's state at an instant of a ``--keep`` run, so that a kept window replays.

A run with ``--keep S`` keeps the last S seconds of its recordings, not the run from t = 0,
so a replay of the window cannot start from ``prerun``. At the start of each recording
segment the supervisor asks every task for its state at a common instant W (a multiple of
every period, a little ahead of the tasks): each task, at the end of its last cycle
released before W, sends a :class:`TaskSnapshot` — the runnable's saved state, ``u`` and
``y`` as they stand, and the cycle it runs next. The recorder keeps it beside the segment
(``NNNNNN-snapshots.pkl``); what survives the flight window ends in ``snapshots/`` of the
run directory, and :func:`rtloop.runtime.replay.replay` starts a window from the earliest
one it can.

The saved state is the runnable's own ``save_state()`` where it has one (every model
runnable: an FMU's serialised FMI state, a 20-sim model's state arrays, a Python model's
attributes), else the runnable's attributes by pickling; beside it, the live values the
task's nudged profile ports hold (they are not in ``u``). What cannot be saved (a 20-sim
member rtloop cannot copy, an attribute that does not pickle) is recorded as a reason: the
replay of that window says so instead of guessing.
"""

from __future__ import annotations

import math
import os
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.ipc.segments import SHM_DIR, open_in_shm, unlink_in_shm
from rtloop.models.base import NOT_STATE
from rtloop.runnable import Runnable

SNAPSHOTS_DIR = "snapshots"
"""In a run directory: the snapshots the flight window kept, one file per recording segment."""
SNAPSHOT_MARGIN_NS = 200_000_000
"""How far ahead of the tasks' newest release the supervisor places W (they must not have passed it)."""


@dataclass(frozen=True)
class TaskSnapshot:
    """One task's state at the instant ``at_ns`` (ns since T0) of a run."""

    task: str
    at_ns: int
    """The instant asked for: the task's state is the one before its first release at or after it."""
    next_cycle: int
    """The cycle the task runs next from this state."""
    last_cycle: int
    """The cycle it finished last (its outputs ``y`` are published with stamp (last_cycle + 1)·P)."""
    u: tuple[float, ...]
    """Its inputs as they stand (the values they keep until read again)."""
    y: tuple[float, ...]
    """Its outputs of ``last_cycle``."""
    state: bytes | None
    """The runnable's saved state (None: it could not be saved, see ``reason``)."""
    reason: str = ""
    """Why ``state`` is None."""
    nudges: tuple[tuple[str, tuple[float, ...]], ...] = ()
    """(port, latest live value) of each of its profile ports taking live nudges (not in ``u``)."""
    outputs: tuple[tuple[int, tuple[float, ...]], ...] = ()
    """(stamp since T0, values) of the samples still in its output channel: a reader that is late
    just after the snapshot may get one older than ``y``, and its replay needs it."""


def save_state(runnable: Runnable) -> tuple[bytes | None, str]:
    """(the runnable's saved state, "") or (None, why it cannot be saved)."""
    own = getattr(runnable, "save_state", None)
    try:
        if own is not None:
            return own(), ""
        return pickle.dumps({k: v for k, v in vars(runnable).items() if k not in NOT_STATE}), ""
    except Exception as error:  # the user's attributes, a model that refuses: say why, never guess
        return None, f"{type(error).__name__}: {error}"


def restore_state(runnable: Runnable, state: bytes) -> None:
    """Give ``runnable`` (after its ``prerun``) a state from :func:`save_state`."""
    own = getattr(runnable, "restore_state", None)
    if own is not None:
        own(state)
    else:
        vars(runnable).update(pickle.loads(state))


def take(task: str, runnable: Runnable, at_ns: int, next_cycle: int, last_cycle: int,
         u: np.ndarray, y: np.ndarray, why_not: str = "",
         nudges: tuple[tuple[str, tuple[float, ...]], ...] = (),
         outputs: tuple[tuple[int, tuple[float, ...]], ...] = ()) -> TaskSnapshot:
    """The snapshot of a task (``why_not``: a reason it cannot be one, known beforehand; ``nudges``:
    the live values its nudged profile ports hold; ``outputs``: the samples still in its channel)."""
    state, reason = (None, why_not) if why_not else save_state(runnable)
    return TaskSnapshot(task, at_ns, next_cycle, last_cycle, tuple(u.tolist()), tuple(y.tolist()), state, reason,
                        nudges, outputs)


def common_instant_ns(after_ns: int, periods_ns: list[int]) -> int:
    """The first instant ≥ ``after_ns`` (ns since T0) that is a release of every task (their LCM grid)."""
    grid = math.lcm(*periods_ns)
    return -(-after_ns // grid) * grid


def read_snapshots(path: Path) -> list[TaskSnapshot]:
    with open(path, "rb") as file:
        snapshots = pickle.load(file)
    if not isinstance(snapshots, list) or not all(isinstance(s, TaskSnapshot) for s in snapshots):
        raise ValueError(f"{path}: not a list of task snapshots")
    return snapshots


# --- from the task to the supervisor, without waiting for it -----------------------------------------


def snapshot_file_name(task_segment: str, wanted_ns: int) -> str:
    """The shared-memory file of a task's snapshot for the request of instant ``wanted_ns`` (CLOCK_MONOTONIC):
    beside the task's segment, so it carries the run's token and goes with a dead run's segments."""
    return f"{task_segment}.snap{wanted_ns}"


def write_snapshot(name: str, snapshot: TaskSnapshot) -> None:
    """Write a task's snapshot into a new file of shared memory (tmpfs: memory, no disk, and no wait on the
    supervisor, which picks it up at its next drain): written under a temporary name, then renamed, so
    the supervisor never reads half of one. Called inside the loop: a pipe there would block on a full
    buffer (64 KiB) until the supervisor reads, and a large FMU state or many outputs fill it."""
    data = pickle.dumps(snapshot, protocol=pickle.HIGHEST_PROTOCOL)
    partial = f"{name}.tmp"
    fd = open_in_shm(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
    finally:
        os.close(fd)
    directory = os.open(SHM_DIR, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        os.rename(partial, name, src_dir_fd=directory, dst_dir_fd=directory)
    finally:
        os.close(directory)


def take_snapshot_file(name: str) -> TaskSnapshot | None:
    """The snapshot in ``name`` (owned by this user, like every segment), removed once read; None while
    the task has not written it."""
    try:
        fd = open_in_shm(name, os.O_RDONLY, owner_uid=os.geteuid())
    except FileNotFoundError:
        return None
    try:
        with os.fdopen(fd, "rb") as file:
            snapshot = pickle.load(file)
    finally:
        unlink_in_shm(name)
    if not isinstance(snapshot, TaskSnapshot):
        raise ValueError(f"{SHM_DIR}/{name}: not a task snapshot")
    return snapshot


def remove_snapshot_files(names: list[str]) -> None:
    """Remove snapshot files nobody will read (and their temporaries): at the end of the run."""
    for name in names:
        for each in (name, f"{name}.tmp"):
            unlink_in_shm(each)


class SnapshotRequests:
    """The supervisor's side of a --keep run's snapshots: at each new recording segment it asks every
    task for its state at a common release a little ahead (so the kept window replays from it), and at
    every drain it hands the snapshots the tasks wrote to the recorder. A bounded number of requests
    wait for their tasks (a task that failed never answers); what is left is removed at the end."""

    WAITING_REQUESTS = 8

    def __init__(self, task_segments: dict[str, str], periods_ns: list[int]) -> None:
        self.task_segments = task_segments
        """Per task, the name of its segment (its snapshot files sit beside it)."""
        self.periods_ns = periods_ns
        self.segment = 0
        """The recording segment whose start the tasks were last asked to snapshot."""
        self.waiting: dict[int, set[str]] = {}
        """Per requested instant (CLOCK_MONOTONIC), the tasks whose snapshot has not come yet."""
        self.problems: list[str] = []

    def collect(self, recorder: Any) -> None:
        for wanted_ns, tasks in self.waiting.items():
            for task in sorted(tasks):
                name = snapshot_file_name(self.task_segments[task], wanted_ns)
                try:
                    snapshot = take_snapshot_file(name)
                except (OSError, ValueError, pickle.UnpicklingError, EOFError) as error:
                    self.problems.append(f"task {task}: its snapshot could not be read ({error}); the kept window "
                                         "may not replay from that instant")
                    tasks.discard(task)
                    continue
                if snapshot is not None:
                    recorder.add_snapshot(snapshot)
                    tasks.discard(task)
        for wanted_ns in [w for w, tasks in self.waiting.items() if not tasks]:
            del self.waiting[wanted_ns]

    def ask(self, control: Any, recorder: Any, t0_ns: int) -> None:
        """A new recording segment: ask for the tasks' state at a common release ahead of them."""
        from rtloop.ipc.status import ControlWord

        segment = recorder.segment_index
        if segment is None or segment == self.segment:
            return
        self.segment = segment
        wanted_ns = t0_ns + common_instant_ns(recorder.latest_ns + SNAPSHOT_MARGIN_NS, self.periods_ns)
        while len(self.waiting) >= self.WAITING_REQUESTS:  # the oldest request's stragglers are given up
            oldest = min(self.waiting)
            remove_snapshot_files([snapshot_file_name(self.task_segments[t], oldest) for t in self.waiting.pop(oldest)])
        self.waiting[wanted_ns] = set(self.task_segments)
        control[ControlWord.SNAPSHOT_NS] = wanted_ns

    def close(self) -> None:
        """Remove the snapshot files nobody took (a task that wrote after the last collect, or never)."""
        for wanted_ns, tasks in self.waiting.items():
            remove_snapshot_files([snapshot_file_name(self.task_segments[t], wanted_ns) for t in tasks])
        self.waiting.clear()
