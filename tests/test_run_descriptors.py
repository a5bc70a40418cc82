"""A library's caller runs many apps in one process: no run may leave descriptors or mappings.

Each ``rtloop.run`` once left about five descriptors open in the caller (two per shared-memory
segment, its mapping's and its own, plus the task's pipe and exit sentinel): a test session
with a limit of 1024 descriptors ran out of them (EMFILE) after some two hundred runs.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import rtloop
from rt_test_runnables import BadPrerun, Counter, StopAt
from rtloop.errors import TaskFailed


def open_descriptors() -> list[str]:
    """What this process holds open (the descriptors' targets: a leak is named in the failure)."""
    targets = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            targets.append(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:  # the directory's own descriptor, closed by now
            pass
    return sorted(targets)


def shm_mappings() -> list[str]:
    """The rtloop shared-memory segments mapped into this process."""
    with open("/proc/self/maps") as maps:
        return sorted(line.split()[-1] for line in maps if "/dev/shm/rtloop-" in line)


def one_task_app(name: str, runnable: rtloop.Runnable) -> rtloop.App:
    app = rtloop.App(f"{name}{os.getpid()}")
    task = app.add_task("c", runnable, period_ns=1_000_000, policy="other")
    if runnable.n_outputs:  # a record queue: one more segment
        app.record(task.y)
    return app


def runs_of_every_ending(tmp_path: Path, index: int) -> None:
    """A run to its duration, a run a task ends early (StopRequested), a run whose prerun raises,
    and a simulation."""
    rtloop.run(one_task_app("fds_full", Counter()), 0.05, tmp_path / f"full{index}")
    summary = rtloop.run(one_task_app("fds_early", StopAt(3)), 5.0, tmp_path / f"early{index}")
    assert "cycle" in summary.stopped_by
    with pytest.raises(TaskFailed, match="sensor not found"):
        rtloop.run(one_task_app("fds_fail", BadPrerun()), 0.05, tmp_path / f"fail{index}")
    rtloop.simulate(one_task_app("fds_sim", Counter()), 0.05, tmp_path / f"sim{index}")


def test_runs_leave_no_descriptors_and_no_mappings(tmp_path: Path) -> None:
    runs_of_every_ending(tmp_path, 0)  # the first run opens what stays for good (multiprocessing's helper)
    descriptors, mappings = open_descriptors(), shm_mappings()
    for index in range(1, 3):  # a leak of a descriptor a run shows after one round; two, for one that alternates
        runs_of_every_ending(tmp_path, index)
    assert open_descriptors() == descriptors
    assert shm_mappings() == mappings == []
