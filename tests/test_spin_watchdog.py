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
    assert int((tmp_path / "out.stuck").read_text()) == 5
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped_by"] == "watchdog" and summary["failure"]["task"] == "spinner"


MARKS_FAILED = textwrap.dedent("""
    import os, signal, types
    from rtloop.errors import WatchdogExpired
    from rtloop.ipc.status import StatusWord, TaskState
    from rtloop.runtime import task as task_module

    status = {StatusWord.STATE: TaskState.RUNNING}
    spinning = types.SimpleNamespace(in_loop=True, status=status)
    task_module._end_a_spin_after(30.0, 31.0, spinning)  # this process never runs at a real-time priority
    try:
        os.kill(os.getpid(), signal.SIGXCPU)  # what the kernel sends at RLIMIT_RTTIME's soft limit
    except WatchdogExpired:
        print(TaskState(status[StatusWord.STATE]).name)
""")


def test_the_kernels_spin_signal_marks_the_task_failed_before_its_loop_leaves_real_time(
        rtloop_env: dict[str, str]) -> None:
    # The loop's way out leaves SCHED_FIFO before the task reports; a supervisor waiting on that core
    # runs at once then, and would take a task still marked RUNNING, with no cycle for the limit, as stuck.
    result = subprocess.run([sys.executable, "-c", MARKS_FAILED], capture_output=True, text=True,
                            env=rtloop_env, timeout=60)
    assert result.stdout.strip() == "FAILED", (result.stdout, result.stderr)
