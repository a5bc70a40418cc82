"""A step that spins at a real-time priority on the supervisor's own core.

The supervisor's watchdog needs CPU time; a busy real-time task on every core it may use never
leaves it any (RT throttling stops the whole real-time class, the supervisor's SCHED_FIFO 1
included). The kernel's RLIMIT_RTTIME, set in the task, ends the spin without the supervisor.
The run goes in a subprocess of its own session: if the spin is not ended, the test kills it
(and fails) instead of leaving a SCHED_FIFO spinner on this machine.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from conftest import other_cpu
from rtloop.app.builder import TaskConfig
from rtloop.errors import StopRequested, WatchdogExpired
from rtloop.ipc.status import StatusWord, TaskState
from rtloop.ipc.wiring import TaskWiringPlan
from rtloop.runnable import Runnable
from rtloop.runtime import task as task_module
from rtloop.runtime import taskrun as taskrun_module
from rtloop.runtime.taskrun import TaskRun

SCRIPT = textwrap.dedent("""
    import os, sys
    import rtloop
    from rtloop.runtime.session import Limits
    from rt_test_runnables import SpinFrom

    cpu, name, out = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    os.sched_setaffinity(0, {cpu})  # the supervisor shares the spinner's core
    app = rtloop.App(name)
    app.add_task("spinner", SpinFrom(5, out + ".stuck"), period_ns=1_000_000, priority=70, cpu=cpu,
                 watchdog_periods=100)
    try:
        rtloop.run(app, 60.0, out, limits=Limits(watchdog_min_s=0.5, watchdog_grace_s=1.0))
    except rtloop.errors.TaskFailed as failed:
        print("FAILED", failed.reason)
""")


@pytest.mark.rt
def test_a_spinning_real_time_step_is_ended_when_it_starves_the_supervisor(tmp_path: Path,
                                                                           rtloop_env: dict[str, str]) -> None:
    script = tmp_path / "spin.py"
    script.write_text(SCRIPT)
    out = tmp_path / "out"
    process = subprocess.Popen(
        [sys.executable, str(script), str(other_cpu()), f"spinwatch{os.getpid()}", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=rtloop_env, start_new_session=True,
    )
    try:
        stdout, stderr = process.communicate(timeout=90)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)  # the supervisor and its spinning task
        process.communicate()
        pytest.fail("the spinning step was not ended: the supervisor starved on its core")
    assert "FAILED" in stdout and "watchdog" in stdout and "RLIMIT_RTTIME" in stdout, (stdout, stderr)
    # it spins from the first cycle it gets at or after 5 (a loaded machine may skip that release)
    assert int((tmp_path / "out.stuck").read_text()) >= 5
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped_by"] == "watchdog" and summary["failure"]["task"] == "spinner"


class RaisesInStep(Runnable):
    n_inputs, n_outputs = 0, 1

    def __init__(self, error: BaseException) -> None:
        self.error = error

    def step(self, u, y) -> None:
        raise self.error


class OneMoreRelease:
    """The framework's share of a cycle reduced to "the next release is here" (no clock, no memory)."""

    def start(self, *_args) -> None: ...
    def begin(self) -> bool: return True
    def finish(self) -> bool: return True
    def close(self) -> None: ...


@pytest.mark.parametrize(("error", "state_when_leaving"), [
    (WatchdogExpired("what SIGXCPU raises (RLIMIT_RTTIME)"), "FAILED"),
    (ZeroDivisionError("a student's step"), "FAILED"),
    (StopRequested("the model's end"), "RUNNING"),  # an orderly end: the caller says it
])
def test_a_loop_ended_by_an_error_marks_the_task_failed_before_it_leaves_real_time(
        monkeypatch, error: BaseException, state_when_leaving: str) -> None:
    # The loop's way out leaves SCHED_FIFO before the task reports; a supervisor waiting on that core
    # runs at once then, and would take a task still marked RUNNING, with no cycle for the limit, as stuck.
    status = {StatusWord.STATE: TaskState.RUNNING}
    run = TaskRun(TaskConfig("spinner", 1_000_000), RaisesInStep(error), TaskWiringPlan(), {}, status,
                  None)  # type: ignore[arg-type]
    task = task_module.RealtimeTask(run)
    monkeypatch.setattr(taskrun_module, "cycle_work", lambda *_args, **_kwargs: OneMoreRelease())
    seen: list[str] = []
    monkeypatch.setattr(task_module.rt, "leave_realtime", lambda: seen.append(TaskState(status[StatusWord.STATE]).name))
    with pytest.raises(type(error)):
        task.run_loop(0, 1_000_000_000)
    assert seen == [state_when_leaving]
