"""Running apps for real: artifacts, RT settings, faults, signals, the unprivileged fallback.

The real-time tests count cycles; in the emulated PREEMPT_RT guest (docs/rtkernel-guest.md)
they run with periods and durations stretched by ``scaled_ns``/``scaled_s``, so the same
number of cycles runs and the same behaviour is asserted, never time itself.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

import rtloop
from conftest import other_cpu, scaled_ns, scaled_s, unique_name, wait_for_app, wait_for_cycles
from rt_test_runnables import BadPrerun, Counter, Noop, RaiseAt, ReportSettings, Sleepy
from rtloop import App, AppError, TaskFailed

P = scaled_ns(1_000_000)  # 1 kHz here, slower where Python is (the emulated guest)


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as file:
        return list(csv.DictReader(file))


@pytest.mark.rt
@pytest.mark.usefixtures("hot_path")
def test_run_writes_summary_and_timing_as_specified(tmp_path: Path) -> None:
    app = App(unique_name("two_counters"))
    a = app.add_task("a", Counter(), period_ns=P, priority=70, cpu=other_cpu())
    app.add_task("b", Noop(), period_ns=2 * P, priority=60, cpu=other_cpu())
    app.record(a.y)
    duration_s = scaled_s(0.5)  # 500 cycles
    summary = rtloop.run(app, duration_s, tmp_path)
    data = json.loads((tmp_path / "summary.json").read_text())
    assert data["app"] == app.name and data["duration_s"] == duration_s and data["rt_capable"] is True
    task = data["tasks"]["a"]
    assert (task["rt"], task["policy"], task["priority"], task["cpu"]) == (True, "fifo", 70, other_cpu())
    for key in ("period_ns", "cycles", "trimmed", "latency_ns", "period_jitter_ns", "exec_ns",
                "deadline_misses", "overruns", "stale_connection_reads", "stale_device_reads", "jitter_over_3pct"):
        assert key in task, key
    assert task["cycles"] + task["overruns"] == 500
    assert data["tasks"]["b"]["cycles"] + data["tasks"]["b"]["overruns"] == 250
    rows = read_csv(tmp_path / "timing.csv")
    assert list(rows[0]) == ["task", "cycle", "release_ns", "start_ns", "end_ns"]
    a_rows = [r for r in rows if r["task"] == "a"]
    assert len(a_rows) == task["cycles"] == summary.tasks["a"].timing.cycles
    for row in a_rows:
        assert int(row["release_ns"]) <= int(row["start_ns"]) <= int(row["end_ns"])
    # phase-aligned: both tasks share the epoch T0
    first_b = next(r for r in rows if r["task"] == "b" and r["cycle"] == "0")
    assert first_b["release_ns"] == next(r for r in a_rows if r["cycle"] == "0")["release_ns"]
    signals = read_csv(tmp_path / "signals.csv")
    assert list(signals[0]) == ["t_s", "a.y[0]", "a.y[1]"]
    # the row at t holds what is valid from t on: the job released at kP publishes at (k+1)P, never
    # sooner; a release a loaded machine skipped has no row (seen once: a stall right after T0 left
    # the first rows at 0 and 36 ms), so the rows that are there are checked, each at its time
    assert signals[0]["t_s"] == "0.0" and float(signals[0]["a.y[0]"]) == 0.0  # initial outputs
    times_s = [float(row["t_s"]) for row in signals]
    assert all(row["t_s"] == repr(round(t_s * 1e9 / P) * P / 1e9) for row, t_s in zip(signals, times_s, strict=True))
    published = [(t_s, float(row["a.y[1]"])) for row, t_s in zip(signals[1:], times_s[1:], strict=True)]
    assert all(t_s >= job_s + P / 1e9 - 1e-12 for t_s, job_s in published), "an output valid before release + P"
    on_time = [t_s for t_s, job_s in published if abs(t_s - job_s - P / 1e9) < 1e-12]
    assert len(on_time) >= len(published) // 2, published[:10]
    if signals[3]["t_s"] == repr(3 * P / 1e9):
        assert float(signals[3]["a.y[1]"]) == 2 * P * 1e-9


@pytest.mark.rt
def test_rt_settings_are_really_applied_in_the_task_process(tmp_path: Path) -> None:
    app = App(unique_name("settings"))
    t = app.add_task("probe", ReportSettings(), period_ns=P, priority=42, cpu=other_cpu(), policy="rr")
    app.record(t.y)
    rtloop.run(app, scaled_s(0.1), tmp_path)
    row = read_csv(tmp_path / "signals.csv")[1]  # [0] holds the initial outputs (t = 0)
    assert float(row["probe.y[0]"]) == os.SCHED_RR
    assert float(row["probe.y[1]"]) == 42
    assert float(row["probe.y[2]"]) == other_cpu()
    assert float(row["probe.y[3]"]) > 1000, "mlockall should lock the whole process (VmLck in kB)"


@pytest.mark.rt
@pytest.mark.usefixtures("hot_path")
def test_exception_in_step_reports_task_cycle_and_traceback_and_keeps_artifacts(tmp_path: Path) -> None:
    app = App(unique_name("faulty"))
    # catch_up: every cycle up to the fault runs even if this loaded machine stalls the task once
    bad = app.add_task("bad", RaiseAt(cycle=123), period_ns=P, cpu=other_cpu(), overrun="catch_up")
    app.add_task("good", Counter(), period_ns=P, cpu=other_cpu(), priority=70)
    app.record(bad.y)
    with pytest.raises(TaskFailed) as caught:
        rtloop.run(app, scaled_s(5), tmp_path)
    failure = caught.value
    assert (failure.task, failure.cycle, failure.phase) == ("bad", 123, "step")
    assert "ZeroDivisionError" in failure.reason and "rt_test_runnables.py" in failure.traceback_text
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["stopped_by"] == "fault"
    assert summary["failure"]["cycle"] == 123 and summary["failure"]["task"] == "bad"
    assert summary["tasks"]["bad"]["cycles"] == 123  # cycles 0..122 completed
    assert summary["tasks"]["good"]["cycles"] < 5000  # the other task was stopped too
    rows = [r for r in read_csv(tmp_path / "timing.csv") if r["task"] == "bad"]
    assert len(rows) == 123
    signals = read_csv(tmp_path / "signals.csv")
    assert float(signals[-1]["bad.y[0]"]) == 122


def test_exception_in_prerun_is_reported_before_the_loop(tmp_path: Path) -> None:
    app = App(unique_name("badprerun"))
    app.add_task("t", BadPrerun(), period_ns=P, policy="other")
    with pytest.raises(TaskFailed, match="sensor not found") as caught:
        rtloop.run(app, 1, tmp_path)
    assert caught.value.phase == "prerun" and caught.value.cycle is None
    assert (tmp_path / "summary.json").exists()


def test_a_runnable_that_cannot_reach_its_process_is_refused_before_running(tmp_path: Path) -> None:
    class HoldsALock(Noop):  # a local class travels by value; a lock held before prerun cannot travel at all
        def __init__(self) -> None:
            self.lock = threading.Lock()

    app = App(f"unsendable_{os.getpid()}")
    app.add_task("t", HoldsALock(), period_ns=P)
    with pytest.raises(AppError, match=r"task 't': HoldsALock cannot be sent to its task process .*prerun"):
        rtloop.run(app, 1, tmp_path / "out")
    assert not (tmp_path / "out").exists()  # refused before anything was written


def _start_cli(app_file: Path, out: Path, env: dict[str, str], duration: float = scaled_s(30)) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", str(duration), "--out", str(out)],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )


def _app_file(tmp_path: Path, name: str) -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(
        f'name = "{name}"\n'
        "[tasks.counter]\n"
        'runnable = "rt_test_runnables:Counter"\n'
        f"period_ns = {P}\npriority = 70\ncpu = {other_cpu()}\n"
        "[tasks.idle]\n"
        'runnable = "rt_test_runnables:Noop"\n'
        f"period_ns = {P}\npriority = 60\ncpu = {other_cpu()}\n"
        "[record]\nsignals = ['counter.y']\n"
    )
    return path


def _wait_running(name: str, process: subprocess.Popen) -> dict[str, int]:
    """The task pids of the app, once its counter has run a few hundred cycles."""
    app = wait_for_app(name, process, scaled_s(60))
    wait_for_cycles(app, "counter", 300, process, scaled_s(60))
    wait_for_cycles(app, "idle", 1, process, scaled_s(60))
    return app.task_pids()


@pytest.mark.rt
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_and_sigterm_stop_cleanly_with_complete_artifacts(tmp_path: Path, rtloop_env, signum) -> None:
    name = unique_name(f"stopme_{signum}")
    process = _start_cli(_app_file(tmp_path, name), tmp_path / "out", rtloop_env)
    _wait_running(name, process)
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=scaled_s(60))
    assert process.returncode == 0, stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["stopped_by"] == "signal" and summary["failure"] is None
    cycles = summary["tasks"]["counter"]["cycles"]
    assert 100 < cycles < 30_000
    rows = [r for r in read_csv(tmp_path / "out" / "timing.csv") if r["task"] == "counter"]
    assert len(rows) == cycles
    assert len(read_csv(tmp_path / "out" / "signals.csv")) == cycles + 1  # and the initial outputs at t = 0
    assert not list(Path("/dev/shm").glob(f"rtloop-{name}-*")), "shared memory left behind"


@pytest.mark.rt
def test_killed_task_process_is_reported_and_the_rest_is_kept(tmp_path: Path, rtloop_env) -> None:
    name = unique_name("killme")
    process = _start_cli(_app_file(tmp_path, name), tmp_path / "out", rtloop_env)
    pids = _wait_running(name, process)
    os.kill(pids["idle"], signal.SIGKILL)
    _, stderr = process.communicate(timeout=scaled_s(60))
    assert process.returncode == 1
    assert "task 'idle' failed" in stderr and "SIGKILL" in stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["failure"]["task"] == "idle" and "SIGKILL" in summary["failure"]["reason"]
    assert summary["tasks"]["counter"]["cycles"] > 100
    assert len([r for r in read_csv(tmp_path / "out" / "timing.csv") if r["task"] == "counter"]) == (
        summary["tasks"]["counter"]["cycles"]
    )


@pytest.mark.rt
@pytest.mark.skipif(shutil.which("setpriv") is None, reason="setpriv (util-linux) is needed to drop privileges")
def test_without_rt_privileges_it_runs_under_sched_other_and_says_why(tmp_path: Path, rtloop_env) -> None:
    app_file = _app_file(tmp_path, unique_name("unprivileged"))
    command = [
        "setpriv", "--inh-caps=-all", "--bounding-set=-all", "--",
        "prlimit", "--rtprio=0", "--memlock=65536", "--",
        sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", str(scaled_s(0.3)),
        "--out", str(tmp_path / "out"),
    ]
    result = subprocess.run(command, env=rtloop_env, capture_output=True, text=True, timeout=scaled_s(60))
    assert result.returncode == 0, result.stderr
    assert "did NOT run real-time" in result.stderr and "did NOT run real-time" not in result.stdout
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["rt_capable"] is False
    task = summary["tasks"]["counter"]
    assert task["rt"] is False and task["policy"] == "other"
    assert "sched_setscheduler" in task["rt_reason"] and "Operation not permitted" in task["rt_reason"]
    # it ran its loop: every release of the 0.3 s either ran or was skipped (SCHED_OTHER on a busy
    # machine skips some; how many is the machine's business, not the test's)
    assert task["cycles"] > 0 and task["cycles"] + task["overruns"] == 300


@pytest.mark.rt
def test_skip_policy_skips_missed_releases_and_counts_them(tmp_path: Path) -> None:
    app = App(unique_name("overrun"))
    slow = app.add_task("slow", Sleepy(scaled_s(0.0035), every=50), period_ns=P, cpu=other_cpu())
    app.record(slow.y)
    summary = rtloop.run(app, scaled_s(0.5), tmp_path)
    timing = summary.tasks["slow"].timing
    sleeps = int(float(read_csv(tmp_path / "signals.csv")[-1]["slow.y[0]"]))
    assert sleeps >= 9
    assert timing.overruns >= 3 * sleeps  # each sleep of 3.5 ms skips at least 3 releases
    assert timing.cycles + timing.overruns == 500
    assert timing.deadline_misses >= sleeps


@pytest.mark.rt
def test_releases_skipped_by_an_overrun_into_the_runs_end_are_counted(tmp_path: Path) -> None:
    """The last cycles overrun into the run's end: the releases they skip before it leave no gap
    in timing.csv (no cycle follows), and still count as overruns (a CI run lacked one of 300)."""
    app = App(unique_name("overrun_at_end"))
    app.add_task("slow", Sleepy(scaled_s(0.0035), every=48), period_ns=P, cpu=other_cpu())
    summary = rtloop.run(app, scaled_s(0.05), tmp_path)
    timing = summary.tasks["slow"].timing
    cycles = [int(r["cycle"]) for r in read_csv(tmp_path / "timing.csv") if r["task"] == "slow"]
    assert max(cycles) >= 48, "the second sleep came at or after release 48, less than 2 periods before the end"
    assert timing.cycles + timing.overruns == 50, (timing.cycles, timing.overruns, cycles[-3:])


@pytest.mark.rt
def test_sched_deadline_runs_with_a_runtime_budget_of_half_the_period(tmp_path: Path) -> None:
    app = App(unique_name("deadline"))
    app.add_task("t", ReportSettings(), period_ns=P, policy="deadline")
    with pytest.raises(AppError, match="cannot be pinned"):
        app.add_task("pinned", Noop(), period_ns=P, policy="deadline", cpu=0)
    summary = rtloop.run(app, scaled_s(0.2), tmp_path)
    task = summary.tasks["t"]
    assert (task.policy, task.rt, task.rt_reason) == ("deadline", True, "")
    assert task.timing.cycles + task.timing.overruns == 200


@pytest.mark.rt
def test_cli_cpu_option_pins_every_task(tmp_path: Path, rtloop_env) -> None:
    app_file = _app_file(tmp_path, unique_name("pinned"))
    duration = str(scaled_s(0.2))
    result = subprocess.run(
        [sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", duration, "--out", str(tmp_path / "o"),
         "--cpu", "0", "-q"], env=rtloop_env, capture_output=True, text=True, timeout=scaled_s(60))
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert {task["cpu"] for task in summary["tasks"].values()} == {0}
    bad = subprocess.run(
        [sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", duration, "--out", str(tmp_path / "o"),
         "--cpu", "99"], env=rtloop_env, capture_output=True, text=True, timeout=scaled_s(60))
    assert bad.returncode == 2 and "cpu 99 is not one of this machine's CPUs" in bad.stderr


def test_cli_reports_a_malformed_app_file_with_the_key(tmp_path: Path, rtloop_env) -> None:
    path = tmp_path / "typo.toml"
    path.write_text('name = "typo"\n[tasks.t]\nrunnable = "rt_test_runnables:Noop"\nperiod_n = 1000000\n')
    result = subprocess.run(
        [sys.executable, "-m", "rtloop.cli", "run", str(path), "--duration", "1", "--out", str(tmp_path / "o")],
        env=rtloop_env, capture_output=True, text=True,
    )
    assert result.returncode == 2
    assert "tasks.t.period_n" in result.stderr and "did you mean 'period_ns'" in result.stderr
