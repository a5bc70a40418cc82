"""A task whose code takes over SIGTERM (a library's handler, a student's "clean exit", SIG_IGN)
still stops in order when its supervisor is killed: the kernel's parent-death signal is one of
rtloop's own, and rtloop puts its handlers back after prerun (saying so in summary.json's notes).
Without that the loop went on commanding its device with no supervisor, until a kill -9 by hand."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import unique_name
from device_test_drivers import read_log

TESTS = Path(__file__).resolve().parent
STUBBORN = '''
import signal

from rtloop import Runnable


class Stubborn(Runnable):
    """Ignores SIGTERM from prerun on, as a library's or a student's own handler may."""

    n_inputs = n_outputs = 1

    def prerun(self):
        signal.signal(signal.SIGTERM, lambda *_: None)

    def step(self, u, y):
        y[0] = u[0] + 1.0
'''
APP = """name = "{name}"
[tasks.ctl]
runnable = "stubborn:Stubborn"
period_ns = 2_000_000
priority = 10
[devices.dev]
kind = "device_test_drivers:LogDevice"
task = "ctl"
log = "{log}"
[devices.dev.limits.c0]
min = -1e6
max = 1e6
safe = -7.0
[[connect]]
from = "ctl.y[0]"
to = "dev.u[0]"
[[connect]]
from = "dev.y[0]"
to = "ctl.u[0]"
"""


def _app(tmp_path: Path, name: str) -> Path:
    (tmp_path / "stubborn.py").write_text(STUBBORN)
    app = tmp_path / "app.toml"
    app.write_text(APP.format(name=unique_name(name), log=tmp_path / "dev.log"))
    return app


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as stat:
        return stat.read().rsplit(")", 1)[1].split()[0] != "Z"


def _gone_within(bound_s: float, pid: int) -> bool:
    end = time.monotonic() + bound_s
    while time.monotonic() < end and _alive(pid):
        time.sleep(0.1)
    return not _alive(pid)


def _end(supervisor: subprocess.Popen[bytes], task_pid: int) -> None:
    """What a test started and left running (after a failure): the supervisor, then the task (0: unknown)."""
    if supervisor.poll() is None:
        supervisor.kill()
        supervisor.wait()
    if task_pid and _alive(task_pid):
        os.kill(task_pid, signal.SIGKILL)


def test_a_task_that_ignores_sigterm_stops_in_order_when_its_supervisor_is_killed(tmp_path: Path) -> None:
    app = _app(tmp_path, "orphan")
    out = tmp_path / "out"
    supervisor = subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app), "--out", str(out)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                                  env=_env())
    task_pid = 0
    try:
        end = time.monotonic() + 60
        while time.monotonic() < end and not any(line.startswith("write ") for line in read_log(tmp_path / "dev.log")):
            time.sleep(0.1)  # the loop runs: its device is written every cycle
        task_pid = int((tmp_path / "dev.log.pid").read_text())
        supervisor.kill()  # SIGKILL: no orderly stop from the supervisor
        supervisor.wait()
        assert _gone_within(30, task_pid), "the task went on running its loop with no supervisor"
        log = read_log(tmp_path / "dev.log")
        assert log[-3:] == ["safe -7.0", "deactivate", "close"], log[-5:]
    finally:
        _end(supervisor, task_pid)


def test_a_run_says_its_code_took_over_sigterm(tmp_path: Path) -> None:
    app = _app(tmp_path, "orphan_note")
    done = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", "0.3", "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, timeout=120, env=_env())
    assert done.returncode == 0, done.stderr
    notes = json.loads((tmp_path / "out" / "summary.json").read_text())["notes"]
    assert any("task ctl: its code replaced rtloop's handler of SIGTERM" in note for note in notes), notes


HANGS = '''
import os
import signal
import time

from rtloop import Runnable


class KillsItsSupervisorThenHangs(Runnable):
    """At cycle 20 (or the first after it), SIGKILLs the supervisor, then its step never returns: it
    sleeps (only a stop signal's exception ends it), or, ``deaf``, with the watchdog's signal blocked
    as a step stuck in C code may be."""

    n_inputs = n_outputs = 1

    def __init__(self, supervisor_pid_file, deaf):
        self.supervisor_pid_file, self.deaf = supervisor_pid_file, deaf

    def step(self, u, y):
        y[0] = u[0] + 1.0
        if self.tick.cycle >= 20:
            if self.deaf:
                signal.pthread_sigmask(signal.SIG_BLOCK, [signal.SIGRTMIN + 6])
            with open(self.supervisor_pid_file) as pid_file:
                os.kill(int(pid_file.read()), signal.SIGKILL)
            while True:
                time.sleep(0.05)
'''
RUNNER = '''
import os
import sys
from pathlib import Path

import rtloop
from hangs import KillsItsSupervisorThenHangs
from rtloop import App
from rtloop.runtime.session import Limits

here = Path(__file__).parent
(here / "supervisor.pid").write_text(str(os.getpid()))
app = App(sys.argv[1])
ctl = app.add_task("ctl", KillsItsSupervisorThenHangs(str(here / "supervisor.pid"), sys.argv[2] == "deaf"),
                   period_ns=2_000_000, policy="other", watchdog_periods=1)
dev = app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(here / "dev.log"),
                     limits={"c0": {"min": -1e6, "max": 1e6, "safe": -7.0}})
app.connect(ctl.y[0], dev.u[0])
app.connect(dev.y[0], ctl.u[0])
rtloop.run(app, None, here / "out", limits=Limits(watchdog_min_s=2.0, watchdog_grace_s=float(sys.argv[3])))
'''


@pytest.mark.parametrize("deaf", [False, True], ids=["step-broken", "process-ended"])
def test_a_step_stuck_after_its_supervisor_died_is_broken_by_the_tasks_own_watchdog(tmp_path: Path,
                                                                                 deaf: bool) -> None:
    """The supervisor SIGKILLed while the step does not return: its watchdog is gone with it, so the
    task's own (kernel timers set at the parent-death signal) breaks the step after the watchdog's
    limit, 2 s here, and the device gets its safe value; a step that cannot be broken (the signal
    blocked) is ended with its process when the supervisor would have killed it. Before, the task
    stayed stuck for good, its device holding the last command."""
    (tmp_path / "hangs.py").write_text(HANGS)
    (tmp_path / "runner.py").write_text(RUNNER)
    grace_s = "1.0" if deaf else "120.0"  # when the process is ended: 2 s + the grace, or well after the test
    env = {**_env(), "PYTHONPATH": os.pathsep.join([str(tmp_path), _env()["PYTHONPATH"]])}
    with open(tmp_path / "stderr.txt", "w") as stderr:  # a file: the task, which may outlive it, holds it too
        supervisor = subprocess.Popen([sys.executable, str(tmp_path / "runner.py"), unique_name("orphan_stuck"),
                                       "deaf" if deaf else "hears", grace_s], stdout=subprocess.DEVNULL,
                                      stderr=stderr, start_new_session=True, env=env)
    task_pid = 0
    try:
        supervisor.wait(timeout=120)  # until the step kills it
        assert supervisor.returncode == -signal.SIGKILL, (tmp_path / "stderr.txt").read_text()
        task_pid = int((tmp_path / "dev.log.pid").read_text())
        assert _gone_within(60, task_pid), "the task stayed stuck with no supervisor"
        log = read_log(tmp_path / "dev.log")
        if deaf:  # SIGKILL: nothing more reached the device (its own watch, or the bus's, has to stop it)
            assert log[-1].startswith("write ") and "safe -7.0" not in log[log.index("activate"):], log[-5:]
        else:
            assert log[-3:] == ["safe -7.0", "deactivate", "close"], log[-5:]
    finally:
        _end(supervisor, task_pid)
