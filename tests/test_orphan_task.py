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
        end = time.monotonic() + 30
        while time.monotonic() < end and _alive(task_pid):
            time.sleep(0.1)
        assert not _alive(task_pid), "the task went on running its loop with no supervisor"
        log = read_log(tmp_path / "dev.log")
        assert log[-3:] == ["safe -7.0", "deactivate", "close"], log[-5:]
    finally:
        if supervisor.poll() is None:
            supervisor.kill()
            supervisor.wait()
        if task_pid and _alive(task_pid):
            os.kill(task_pid, signal.SIGKILL)


def test_a_run_says_its_code_took_over_sigterm(tmp_path: Path) -> None:
    app = _app(tmp_path, "orphan_note")
    done = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", "0.3", "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, timeout=120, env=_env())
    assert done.returncode == 0, done.stderr
    notes = json.loads((tmp_path / "out" / "summary.json").read_text())["notes"]
    assert any("task ctl: its code replaced rtloop's handler of SIGTERM" in note for note in notes), notes
