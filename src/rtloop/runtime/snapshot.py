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
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
