"""A terminal that closes (an SSH connection dropping, a tmux server killed) sends SIGHUP: the run
stops the orderly way, as with Ctrl-C or SIGTERM — safe values, the recording joined, summary.json
``stopped_by: signal``, exit 0 — and its console lines, with nowhere to go, are dropped."""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
import termios
import time
from pathlib import Path

from conftest import unique_name

TESTS = Path(__file__).resolve().parent
APP = """name = "{name}"
[tasks.count]
runnable = "rt_test_runnables:Counter"
period_ns = 2_000_000
priority = 10
[tasks.slow]
runnable = "rt_test_runnables:Noop"
period_ns = 20_000_000
priority = 10
[record]
signals = ["count.y"]
"""


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}


def _wait_running(out: Path, deadline_s: float = 60) -> None:
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        try:
            if json.loads((out / "summary.json").read_text()).get("running"):
                return
        except (OSError, ValueError):
            pass
        time.sleep(0.1)
    raise AssertionError(f"the run never started: {list(out.iterdir()) if out.exists() else 'no folder'}")


def _assert_ended_in_order(out: Path) -> None:
    summary = json.loads((out / "summary.json").read_text())
    assert summary["running"] is False and summary["stopped_by"] == "signal", summary
    for artifact in ("timing.csv", "signals.csv", "metadata.yaml"):
        assert (out / artifact).exists(), artifact
    assert not (out / "segments").exists()  # the recording was joined


def test_a_terminal_that_closes_stops_the_run_in_order(tmp_path: Path) -> None:
    app = tmp_path / "app.toml"
    app.write_text(APP.format(name=unique_name("hup_tty")))
    out = tmp_path / "out"
    master, slave = os.openpty()

    def own_terminal() -> None:  # as a login shell's child: its own session, the pty its terminal
        os.setsid()
        fcntl.ioctl(slave, termios.TIOCSCTTY, 0)

    run = subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app), "--out", str(out)], stdin=slave,
                           stdout=slave, stderr=slave, preexec_fn=own_terminal, env=_env())
    os.close(slave)
    try:
        _wait_running(out)
        os.close(master)  # the terminal goes away: the kernel sends SIGHUP (then writes to it fail)
        master = -1
        assert run.wait(timeout=60) == 0
    finally:
        if master >= 0:
            os.close(master)
        if run.poll() is None:
            run.kill()
            run.wait()
    _assert_ended_in_order(out)


def test_sighup_to_the_process_group_with_output_to_a_file(tmp_path: Path) -> None:
    app = tmp_path / "app.toml"
    app.write_text(APP.format(name=unique_name("hup_file")))
    out = tmp_path / "out"
    with open(tmp_path / "console.log", "w") as log:
        run = subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app), "--out", str(out)],
                               stdout=log, stderr=subprocess.STDOUT, start_new_session=True, env=_env())
        try:
            _wait_running(out)
            os.killpg(run.pid, signal.SIGHUP)  # what a closing terminal sends: to every process of the group
            assert run.wait(timeout=60) == 0, (tmp_path / "console.log").read_text()
        finally:
            if run.poll() is None:
                run.kill()
                run.wait()
    _assert_ended_in_order(out)
