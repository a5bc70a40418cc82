"""Lifecycle bugs around the real-time loop (issue 29): each test here failed before its fix."""

from __future__ import annotations

import csv
import os
import re
import signal
import threading
from pathlib import Path

import pytest

import rtloop
from rt_test_runnables import Counter, FailsWithSlowPostrun
from rtloop import App
from rtloop.errors import TaskFailed
from rtloop.runtime.session import Limits

PERIOD_NS = 10_000_000
FAIL_CYCLE = 20


def _releases_of(out: Path, task: str) -> list[int]:
    with open(out / "timing.csv", newline="") as file:
        return [int(row["release_ns"]) for row in csv.DictReader(file) if row["task"] == task]


def _failed_at_ns(failure: TaskFailed) -> int:
    match = re.search(r"failed at (\d+) ns", failure.reason)
    assert match, failure.reason
    return int(match.group(1))


@pytest.mark.parametrize("postrun_s", [2.5, None], ids=["slow-postrun", "hung-postrun"])
def test_a_failed_task_stops_the_healthy_one_within_two_of_its_periods(tmp_path: Path, postrun_s: float | None) -> None:
    """Task A fails at cycle 20 and then spends 2.5 s in postrun (or hangs there, in a run without a
    duration): task B must not go on meanwhile (its devices would be driven from A's last outputs)."""
    app = App(f"failstop_{os.getpid()}_{'hung' if postrun_s is None else 'slow'}")
    app.add_task("a", FailsWithSlowPostrun(FAIL_CYCLE, postrun_s), period_ns=PERIOD_NS)
    app.add_task("b", Counter(), period_ns=PERIOD_NS)
    duration_s = None if postrun_s is None else 10.0
    # Before the fix a hung postrun kept the app running for ever: a Ctrl-C after 20 s ends the test.
    rescue = threading.Timer(20.0, os.kill, (os.getpid(), signal.SIGINT))
    rescue.start()
    try:
        with pytest.raises(TaskFailed) as failed:
            rtloop.run(app, duration_s, tmp_path / "out", limits=Limits(stop_grace_s=1.0))
    finally:
        rescue.cancel()
    assert failed.value.task == "a" and failed.value.phase == "step"
    failed_at_ns = _failed_at_ns(failed.value)
    late = [release for release in _releases_of(tmp_path / "out", "b") if release > failed_at_ns + 2 * PERIOD_NS]
    assert late == [], f"b ran {len(late)} cycles released more than 2 periods after a's failure"


# --- stop requests are counted, not read from the STOP flag ----------------------------------------


def test_a_sigterm_to_a_task_after_the_supervisors_stop_is_an_orderly_stop_not_a_fault(tmp_path: Path) -> None:
    """A process-group SIGTERM reaches the supervisor and the task: when the supervisor's handler has
    set STOP first, the task's own SIGTERM is still its first request (before: "a second request",
    which broke the step of a task with devices and turned the orderly stop into a fault)."""
    import subprocess
    import sys
    import time

    from device_test_drivers import read_log

    app_file = tmp_path / "app.toml"
    app_file.write_text(f"""
name = "sigterm_race_{os.getpid()}"
[tasks.ctl]
runnable = "device_test_drivers:Echo"
args = {{ slow_s = 3.0 }}
period_ns = 2_000_000
policy = "other"
[devices.dev]
kind = "device_test_drivers:LogDevice"
task = "ctl"
log = "{tmp_path / 'dev.log'}"
limits.c0 = {{min = -1e6, max = 1e6, safe = -7.0}}
[[connect]]
from = "ctl.y[0]"
to = "dev.u[0]"
""")
    process = subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app_file), "--out", str(tmp_path / "out"),
                                "--quiet"], cwd=Path(__file__).parent, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not any(line.startswith("write ") for line in read_log(tmp_path / "dev.log")):
            assert process.poll() is None and time.monotonic() < deadline, process.communicate()
            time.sleep(0.01)
        # the first step has begun (its device was written at the release); it sleeps 3 s
        process.send_signal(signal.SIGTERM)  # the supervisor first: it sets STOP
        time.sleep(0.3)
        os.kill(int((tmp_path / "dev.log.pid").read_text()), signal.SIGTERM)  # then the task, mid-step
        _out, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 0, err
    summary = (tmp_path / "out" / "summary.json").read_text()
    assert '"stopped_by": "signal"' in summary and '"failure": null' in summary
    assert read_log(tmp_path / "dev.log")[-3:] == ["safe -7.0", "deactivate", "close"]


class _Task:
    devices = True
    in_loop = True


def test_requests_are_counted_the_supervisors_death_once_the_watchdogs_signal_breaks_the_step() -> None:
    from rtloop.ipc.status import ControlWord
    from rtloop.runtime.task import STEP_STUCK, SUPERVISOR_GONE, StopRequests

    control = {ControlWord.STOP: 1}  # set by someone else: no request of this process's yet
    requests = StopRequests(control)  # type: ignore[arg-type]
    requests.task = _Task()  # type: ignore[assignment]
    requests(SUPERVISOR_GONE, None)
    requests(SUPERVISOR_GONE, None)  # the kernel said it twice (once per exiting supervisor thread)
    assert requests.count == 1
    with pytest.raises(TimeoutError, match="a second stop request"):
        requests(signal.SIGTERM, None)
    watchdog = StopRequests(control)  # type: ignore[arg-type]
    watchdog.task = _Task()  # type: ignore[assignment]
    with pytest.raises(TimeoutError, match="the watchdog"):
        watchdog(STEP_STUCK, None)  # its first signal: the step is stuck, break it


# --- simulate: postrun always, once --------------------------------------------------------------


class _CountsPostrun(Counter):
    def __init__(self) -> None:
        super().__init__()
        self.postruns = 0

    def postrun(self) -> None:
        self.postruns += 1


def test_simulate_calls_every_postrun_once_after_a_fault(tmp_path: Path) -> None:
    from rt_test_runnables import RaiseAt

    app = App(f"simpostrun_{os.getpid()}")
    failing, healthy = RaiseAt(5), _CountsPostrun()
    failing.postruns = 0  # type: ignore[attr-defined]
    failing.postrun = lambda: setattr(failing, "postruns", failing.postruns + 1)  # type: ignore[method-assign]
    app.add_task("failing", failing, period_ns=PERIOD_NS)
    app.add_task("healthy", healthy, period_ns=PERIOD_NS)
    with pytest.raises(TaskFailed) as failed:
        rtloop.simulate(app, 0.2, tmp_path / "out")
    assert failed.value.task == "failing" and failed.value.cycle == 5
    assert (failing.postruns, healthy.postruns) == (1, 1)  # type: ignore[attr-defined]


@pytest.mark.parametrize("mode", ["run", "simulate"])
def test_a_postrun_that_fails_after_the_failure_is_a_note_not_lost(tmp_path: Path, mode: str) -> None:
    """The step fails, then postrun raises as well: the run's failure stays the step's, and
    summary.json's notes say the postrun failed too (the task's message was never read; simulate
    dropped what finish returned)."""
    import json

    from rt_test_runnables import RaiseAtThenInPostrun

    app = App(f"postrunfail_{mode}_{os.getpid()}")
    app.add_task("failing", RaiseAtThenInPostrun(3), period_ns=PERIOD_NS, policy="other")
    with pytest.raises(TaskFailed) as failed:
        (rtloop.run if mode == "run" else rtloop.simulate)(app, 0.5, tmp_path / "out")
    assert failed.value.task == "failing" and "ZeroDivisionError" in failed.value.reason
    notes = json.loads((tmp_path / "out" / "summary.json").read_text())["notes"]
    assert "task failing: its postrun failed too, after the failure: OSError: postrun could not close the port" \
        in notes, notes


def test_simulate_terminates_an_fmu_and_removes_its_folder_after_a_fault(tmp_path: Path, monkeypatch) -> None:
    import shutil

    if shutil.which("gcc") is None:
        pytest.skip("gcc not installed: cannot build the JIWY FMU")
    pytest.importorskip("fmpy")
    import fmpy

    from rt_test_runnables import RaiseAt
    from rtloop.models import load_model
    from rtloop.models.fmu_build import build_fmu

    models = Path(__file__).resolve().parents[1] / "examples" / "jiwy" / "models"
    fmu = build_fmu(models / "fmu", tmp_path / "JiwyPlant.fmu")
    extracted: list[str] = []
    extract = fmpy.extract

    def recorded_extract(*args, **kwargs):
        folder = extract(*args, **kwargs)
        extracted.append(folder)
        return folder

    monkeypatch.setattr(fmpy, "extract", recorded_extract)
    app = App(f"simfmu_{os.getpid()}")
    plant = app.add_task("plant", load_model(f"fmu:{fmu}"), period_ns=PERIOD_NS)
    app.add_task("failing", RaiseAt(5), period_ns=PERIOD_NS)
    app.record(plant.y)
    with pytest.raises(TaskFailed):
        rtloop.simulate(app, 0.2, tmp_path / "out")
    assert extracted and not any(Path(folder).exists() for folder in extracted), "the FMU's folder leaked"


# --- a --keep snapshot never waits for the supervisor -------------------------------------------------


def test_a_large_keep_snapshot_does_not_block_the_loop_while_the_supervisor_is_away(tmp_path: Path) -> None:
    """The snapshot (~320 KiB) went through a blocking pipe from inside the loop: with a supervisor
    that looks every 2 s, the loop waited for it (~1.8 s) — the misses the flight recorder then kept."""
    import json
    import pickle

    from rt_test_runnables import BigState

    app = App(f"bigsnap_{os.getpid()}")
    task = app.add_task("big", BigState(), period_ns=PERIOD_NS, policy="other")
    app.record(task.y)
    rtloop.run(app, 5.0, tmp_path / "out", keep_s=1.2, limits=Limits(drain_interval_s=2.0))
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    latency_max_s = summary["tasks"]["big"]["latency_ns"]["max"] / 1e9
    assert latency_max_s < 1.0, f"a release started {latency_max_s:.2f} s late: the loop waited for the supervisor"
    kept = [s for path in sorted((tmp_path / "out" / "snapshots").glob("*")) for s in pickle.loads(path.read_bytes())]
    assert kept and all(s.state is not None for s in kept), "the snapshot did not reach the run's folder"
    assert not list(Path("/dev/shm").glob(f"rtloop-{app.name}-*")), "a snapshot file was left behind"
