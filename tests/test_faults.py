"""Fault injection: a runnable that raises, exits, segfaults, forks or hangs in each phase,
and a supervisor killed with SIGKILL or stopped with SIGSTOP. Whatever happens, the run
ends with the fault reported in the right phase (and cycle), nothing left in /dev/shm and
no process of the app left running. (A killed ROS 2 bridge: tests/test_ros_app.py.)
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import cli_env
from rtloop.ipc.ports import connect_app

SHM = Path("/dev/shm")
AT_CYCLE = 100
"""The step fault's cycle, 200 ms after T0: the fault stops the other task at once, which must have run a cycle
by then (its summary says so); at cycle 5 (10 ms) a loaded machine that woke it late left it none."""


def _app_file(tmp_path: Path, name: str, phase: str, kind: str) -> Path:
    path = tmp_path / f"{name}.toml"
    pid_file = tmp_path / "forked.pid"
    path.write_text(
        f'name = "{name}"\n'
        "[tasks.faulty]\n"
        'runnable = "rt_test_runnables:Fault"\n'
        f'args = {{ phase = "{phase}", kind = "{kind}", at_cycle = {AT_CYCLE}, pid_file = "{pid_file}" }}\n'
        "period_ns = 2_000_000\npolicy = \"other\"\noverrun = \"catch_up\"\n"
        "[tasks.steady]\n"
        'runnable = "rt_test_runnables:Counter"\n'
        "period_ns = 2_000_000\npolicy = \"other\"\noverrun = \"catch_up\"\n"
    )
    return path


def _command(app_file: Path, out: Path, duration_s: float) -> list[str]:
    return [sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", str(duration_s),
            "--out", str(out), "-q"]


def _run(app_file: Path, out: Path, env: dict[str, str], duration_s: float,
         timeout_s: float) -> subprocess.CompletedProcess:
    return subprocess.run(_command(app_file, out, duration_s), env=env, capture_output=True, text=True,
                          timeout=timeout_s)


def _start(app_file: Path, out: Path, env: dict[str, str], duration_s: float) -> subprocess.Popen:
    return subprocess.Popen(_command(app_file, out, duration_s), env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _gone(pid: int, within_s: float = 10.0) -> bool:
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        try:  # a zombie waiting for init is gone too
            if Path(f"/proc/{pid}/stat").read_text().rsplit(") ", 1)[1][:1] in "ZX":
                return True
        except (OSError, IndexError):
            return True
        time.sleep(0.05)
    return False


# The hangs last: each waits seconds for a limit doing nothing, in the background meanwhile (hung_runs)
CASES = [(phase, kind) for kind in ("raise", "exit", "segfault", "fork") for phase in ("prerun", "step", "postrun")]
HANGS = [(phase, "hang") for phase in ("prerun", "step", "postrun")]


def _hang_env(phase: str, env: dict[str, str]) -> dict[str, str]:
    if phase == "prerun":  # the start-up allowance ends a hung prerun: 5 s, not 30, here
        return {**env, "RTLOOP_STARTUP_ALLOWANCE_S": "5"}
    return env


@pytest.fixture(scope="module")
def hung_runs(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory):
    """The selected hang cases, started together when this module's first fault test starts.

    A hung run spends seconds waiting for a limit (the start-up allowance, or the stop grace
    after its duration) with its processes asleep, so the hangs wait beside the other cases,
    not after them. Each hang test then checks its own run as the other cases do."""
    selected = {(item.callspec.params["phase"], item.callspec.params["kind"]) for item in request.session.items
                if item.module is request.module and hasattr(item, "callspec")}
    runs: dict[tuple[str, str], tuple[Path, str, subprocess.Popen]] = {}
    try:
        for phase, kind in HANGS:
            if (phase, kind) in selected:
                tmp_path = tmp_path_factory.mktemp(f"{phase}-{kind}")
                name = f"fault_{phase}_{kind}_{os.getpid()}"
                process = _start(_app_file(tmp_path, name, phase, kind), tmp_path / "out",
                                 _hang_env(phase, cli_env()), 0.5)
                runs[(phase, kind)] = (tmp_path, name, process)
        yield runs
    finally:
        # Left running when a test failed before its own ended, or when its test ran in another xdist worker
        # (each worker that runs a test of this module starts every selected hang). Each run ends by itself
        # within its limit; killing the supervisor first would leave its hung task holding the pipes, and
        # communicate() waited for them until the suite's timeout.
        for _tmp_path, _name, process in runs.values():
            try:
                process.communicate(timeout=120)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


@pytest.mark.parametrize(("phase", "kind"), [*CASES, *(pytest.param(*case, marks=pytest.mark.slow) for case in HANGS)])
def test_fault_in_each_phase_is_reported_there_and_leaves_nothing(tmp_path: Path, rtloop_env, hung_runs,
                                                                   phase, kind) -> None:
    if kind == "hang":
        tmp_path, name, process = hung_runs[(phase, kind)]
        try:
            stdout, stderr = process.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            process.kill()
            stdout, stderr = process.communicate()
        done = subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)
    else:
        name = f"fault_{phase}_{kind}_{os.getpid()}"
        done = _run(_app_file(tmp_path, name, phase, kind), tmp_path / "out", rtloop_env, duration_s=0.5,
                    timeout_s=120)
    out = tmp_path / "out"
    assert "Traceback" not in done.stderr or kind == "raise", done.stderr  # only the runnable's own, when it raised
    summary = json.loads((out / "summary.json").read_text())
    failure = summary["failure"]
    if kind == "fork":
        assert done.returncode == 0, done.stderr
        forked = int((tmp_path / "forked.pid").read_text())
        assert _gone(forked), f"process {forked} forked in {phase} outlived the app"
    else:
        assert done.returncode == 1, done.stderr
        assert failure["task"] == "faulty" and failure["phase"] == phase, failure
        if phase == "step":
            assert failure["cycle"] == AT_CYCLE, failure  # the cycle it happened in, not the one before
        expected = {"raise": "RuntimeError", "exit": "exit code 3", "segfault": "SIGSEGV", "hang": "did not"}
        assert expected[kind] in failure["reason"], failure
        assert f"failed in {phase}" in done.stderr
    assert summary["tasks"]["steady"]["cycles"] > 0 or phase == "prerun"
    assert not list(SHM.glob(f"rtloop-{name}-*")), "shared memory left behind"


def _task_pids(name: str) -> dict[str, int]:
    app = connect_app(name, timeout_s=30)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        pids = app.task_pids()
        if all(pids.values()):
            return pids
        time.sleep(0.05)
    raise AssertionError("tasks did not start")


@pytest.mark.alone  # another process's run would remove the dead run's segments before this test looks
def test_supervisor_killed_with_sigkill_leaves_no_process_and_the_next_run_cleans_up(tmp_path: Path,
                                                                                      rtloop_env) -> None:
    name = f"kill9_{os.getpid()}"
    process = _start(_app_file(tmp_path, name, "prerun", "fork"), tmp_path / "out", rtloop_env, 60)
    try:
        pids = _task_pids(name)
        forked_file = tmp_path / "forked.pid"
        deadline = time.monotonic() + 20
        while not forked_file.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        forked = int(forked_file.read_text())
        process.send_signal(signal.SIGKILL)
        process.communicate(timeout=10)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    for pid in [*pids.values(), forked]:
        assert _gone(pid), f"process {pid} outlived its killed supervisor"
    left = list(SHM.glob(f"rtloop-{name}-*"))
    assert left, "a killed supervisor cannot clean up: the next run must"
    again = _run(_app_file(tmp_path, f"{name}_next", "step", "fork"), tmp_path / "next", rtloop_env, 0.3, 120)
    assert again.returncode == 0, again.stderr
    assert not list(SHM.glob(f"rtloop-{name}-*")), "the next run left a dead run's segments behind"


def test_supervisor_stopped_with_sigstop_finishes_after_sigcont(tmp_path: Path, rtloop_env) -> None:
    name = f"sigstop_{os.getpid()}"
    process = _start(_app_file(tmp_path, name, "step", "fork"), tmp_path / "out", rtloop_env, 1)
    try:
        _task_pids(name)
        process.send_signal(signal.SIGSTOP)
        time.sleep(2)  # past the run's end (1 s after T0): the tasks end on their own timeline
        process.send_signal(signal.SIGCONT)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["failure"] is None and summary["tasks"]["steady"]["cycles"] > 0
    assert not list(SHM.glob(f"rtloop-{name}-*"))
