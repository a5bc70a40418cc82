"""The supervisor's view of its task processes: one record per process, and the watchdog.

A task whose ``CYCLE`` status word stands still for ``watchdog_periods`` periods (never less
than ``Limits.watchdog_min_s``) is stuck: the supervisor fails the run, stops the other tasks
and sends the stuck one ``STEP_STUCK``; the kernel's RLIMIT_RTTIME is the same limit inside the
task, for a step spinning at a real-time priority that leaves the supervisor no CPU time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rtloop.app.builder import App
from rtloop.errors import TaskFailed
from rtloop.ipc.status import StatusWord, TaskState
from rtloop.linux import rt
from rtloop.linux.hygiene import why_stuck
from rtloop.runtime.layout import AppLayout
from rtloop.runtime.session import Limits


@dataclass
class TaskProcess:
    """The supervisor's record of one task process."""

    name: str
    process: Any
    pipe: Any
    settings: rt.AppliedSettings | None = None
    locked_bytes: int | None = None  # memory the process holds locked once its loop's memory is (linux/memory.py)
    failure: TaskFailed | None = None
    finished: bool = False
    stop_request: str | None = None
    progress_cycle: int = -1  # the CYCLE status word when the watchdog last saw it change
    progress_ns: int = 0  # and when that was
    stuck: bool = False  # the watchdog gave up on it: its signal (STEP_STUCK) sent, SIGKILL follows


class Watchdog:
    """Finds a running task whose cycle count has stood still too long."""

    def __init__(self, app: App, limits: Limits) -> None:
        self.app, self.limits = app, limits

    def limit_ns(self, config: Any) -> int:
        """How long a task may go without finishing a cycle: its periods, never under the minimum."""
        return int(max(config.watchdog_periods * config.period_ns, round(self.limits.watchdog_min_s * 1e9)))

    def spin_limit_s(self, config: Any) -> tuple[float, float] | None:
        """The kernel's side of the watchdog (RLIMIT_RTTIME in the task): the same limit, then the grace."""
        if not config.watchdog_periods:
            return None
        limit_s = self.limit_ns(config) / 1e9
        return limit_s, limit_s + self.limits.watchdog_grace_s

    def orphan_limits_s(self, config: Any) -> tuple[float | None, float]:
        """What a task does on its own once this supervisor died (runtime/task.py, StopRequests): after
        the watchdog's limit it breaks a step that has not returned (None: the watchdog is off), and it
        ends its process when this supervisor would have killed it, the watchdog's grace or the stop's
        grace later."""
        stop_by_s = self.limits.stop_grace_s + config.period_ns / 1e9
        if not config.watchdog_periods:
            return None, stop_by_s
        stuck_after_s = self.limit_ns(config) / 1e9
        return stuck_after_s, max(stop_by_s, stuck_after_s + self.limits.watchdog_grace_s)

    def find_stuck(self, runs: dict[str, TaskProcess], layout: AppLayout, recorder: Any,
                   t0_ns: int) -> tuple[TaskProcess, TaskFailed] | None:
        """The first stuck task and its failure (it is marked stuck), or None."""
        now_ns = rt.now_ns()
        for task_run in runs.values():
            status = layout.tasks[task_run.name].status
            if task_run.finished or task_run.stuck or status[StatusWord.STATE] != TaskState.RUNNING:
                continue
            cycle = status[StatusWord.CYCLE]
            if cycle != task_run.progress_cycle:
                task_run.progress_cycle, task_run.progress_ns = cycle, now_ns
                continue
            config = self.app.tasks[task_run.name].config
            if not config.watchdog_periods:
                continue
            quiet_ns = now_ns - max(task_run.progress_ns, t0_ns)
            if quiet_ns <= self.limit_ns(config):
                continue
            task_run.stuck = True
            return task_run, TaskFailed(
                task_run.name, self.cycle_after(task_run.name, recorder, t0_ns), "step",
                f"watchdog: no cycle finished for {quiet_ns / 1e9:.1f} s ({config.watchdog_periods} periods); "
                f"{why_stuck(task_run.process.pid)}",
            )
        return None

    def cycle_after(self, name: str, recorder: Any, t0_ns: int) -> int:
        """The cycle a task works on: the one after its newest timing record."""
        last = recorder.last_record[name]
        if last is None:
            return 0
        cycle, release_ns, _start_ns, end_ns = last
        config = self.app.tasks[name].config
        if end_ns <= release_ns + config.period_ns or config.overrun == "catch_up":
            return int(cycle) + 1
        return int(end_ns - t0_ns) // config.period_ns + 1  # skip: the next release after it ended


def phase_of(layout: AppLayout, app: App, name: str, t0_ns: int) -> tuple[str, int | None]:
    """What a task was doing when it died or hung: its phase and, in step, the cycle in progress."""
    handles = layout.tasks[name]
    state = handles.status[StatusWord.STATE]
    if state in (TaskState.STARTING, TaskState.READY):
        return "prerun", None
    if state == TaskState.POSTRUN:
        return "postrun", None
    if state == TaskState.STOPPED:
        return "process", None
    return "step", cycle_in_progress(handles, t0_ns, app.tasks[name].config)


def cycle_in_progress(handles: Any, t0_ns: int, config: Any) -> int:
    """The cycle a running task was in: the one after its last completed cycle (the status
    block holds the last completed one), or after the releases an overrun skipped."""
    status = handles.status
    if handles.timing.written_total == 0:
        return 0
    last = status[StatusWord.CYCLE]
    period_ns = config.period_ns
    last_end_ns = t0_ns + last * period_ns + status[StatusWord.LATENCY_LAST_NS] + status[StatusWord.EXEC_LAST_NS]
    following = last + 1
    if config.overrun == "skip" and t0_ns and last_end_ns > t0_ns + following * period_ns:
        following = (last_end_ns - t0_ns) // period_ns + 1
    return int(following)
