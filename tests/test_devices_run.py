"""Devices in a running app: when they are read and written, the safe state on every way out."""

from __future__ import annotations

import csv
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name
from device_test_drivers import Echo, MirrorTwin, read_log
from replay_helpers import compare_signals, first_miss_s
from rt_test_runnables import RaiseAt
from rtloop import App
from rtloop.errors import DeviceError, TaskFailed
from rtloop.runtime.session import Limits

PERIOD_NS = 2_000_000
LIMIT = {"min": -1e6, "max": 1e6, "safe": -7.0}
TESTS = Path(__file__).parent


def echo_app(tmp_path: Path, name: str, *, io: str = "let", echo: Echo | None = None, gain: float = 1.0,
             **task_options) -> App:
    """Task ``ctl`` computes y = u + 1; device ``dev`` writes it and reads back gain × it; the app is
    named ``name`` and this test run's pid (apps here hold their name while they run)."""
    app = App(unique_name(name))
    ctl = app.add_task("ctl", echo or Echo(), period_ns=PERIOD_NS, **task_options)
    dev = app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", io=io, log=str(tmp_path / "dev.log"),
                         gain=gain, twin=MirrorTwin(1, gain), limits={"c0": LIMIT})
    app.connect(ctl.y[0], dev.u[0])
    app.connect(dev.y[0], ctl.u[0])
    app.record(ctl.y, ctl.u)
    return app


def signals(out: Path) -> list[dict[str, str]]:
    with open(out / "signals.csv") as stream:
        return list(csv.DictReader(stream))


def writes(log: list[str]) -> list[float]:
    return [float(line.split()[1]) for line in log if line.startswith("write ")]


def assert_ends_safe(log: list[str]) -> None:
    """The last value on the wire is the safe value, then the device is let go."""
    assert log[-3:] in (["safe -7.0", "deactivate", "close"],), log[-5:]
    assert not any("nan" in line or "inf" in line for line in log)


@pytest.mark.parametrize("io", ["let", "immediate"])
def test_let_writes_the_commands_of_the_job_before_and_immediate_writes_at_once(tmp_path: Path, io: str) -> None:
    app = echo_app(tmp_path, f"dev_timing_{io}", io=io)
    rtloop.run(app, 0.2, tmp_path / "run")
    log = read_log(tmp_path / "dev.log")
    assert log[:3] == ["configure", "safe -7.0", "activate"]
    assert_ends_safe(log)
    rtloop.simulate(echo_app(tmp_path, f"dev_timing_sim_{io}", io=io), 0.2, tmp_path / "sim")
    simulated = [float(r["ctl.y[0]"]) for r in signals(tmp_path / "sim")[1:4]]  # from t = P
    if io == "let":
        # release k: write y of job k-1 (y = 0 before the first job), read it back, y_k = that + 1
        assert writes(log)[:4] == [0.0, 1.0, 2.0, 3.0]
        assert simulated == [1.0, 2.0, 3.0]
    else:
        # release k: read what job k-1 wrote right after its step (before the first: the safe -7)
        assert writes(log)[:3] == [-6.0, -5.0, -4.0]
        assert simulated == [-6.0, -5.0, -4.0]
    assert 4 <= len(writes(log)) <= 100


def test_a_run_equals_its_simulation_with_the_twin(tmp_path: Path) -> None:
    rtloop.simulate(echo_app(tmp_path, "dev_same_sim", gain=0.5), 0.1, tmp_path / "sim")
    rtloop.run(echo_app(tmp_path, "dev_same_run", gain=0.5), 0.1, tmp_path / "run")
    miss_s = first_miss_s(tmp_path / "run")
    compared, difference = compare_signals(tmp_path / "run" / "signals.csv", tmp_path / "sim" / "signals.csv", miss_s)
    assert difference is None, f"run and simulation differ at t = {difference} s (first miss: {miss_s})"
    assert compared >= (10 if miss_s is None else 1)
    assert_ends_safe(read_log(tmp_path / "dev.log"))


# --- every way a run ends writes the safe state ------------------------------------------------------

def test_duration(tmp_path: Path) -> None:
    rtloop.run(echo_app(tmp_path, "dev_stop_duration"), 0.05, tmp_path / "out")
    assert_ends_safe(read_log(tmp_path / "dev.log"))


def test_a_fault_in_the_owner_task(tmp_path: Path) -> None:
    with pytest.raises(TaskFailed, match="ZeroDivisionError"):
        rtloop.run(echo_app(tmp_path, "dev_stop_raise", echo=Echo(raise_at=5)), 1.0, tmp_path / "out")
    assert_ends_safe(read_log(tmp_path / "dev.log"))


def test_a_fault_in_another_task(tmp_path: Path) -> None:
    app = echo_app(tmp_path, "dev_stop_other")
    app.add_task("other", RaiseAt(5), period_ns=PERIOD_NS)
    with pytest.raises(TaskFailed, match="'other'"):
        rtloop.run(app, 5.0, tmp_path / "out")
    assert_ends_safe(read_log(tmp_path / "dev.log"))


def test_a_non_finite_command_never_reaches_the_device(tmp_path: Path) -> None:
    with pytest.raises(TaskFailed) as caught:
        rtloop.run(echo_app(tmp_path, "dev_stop_nan", echo=Echo(nan_at=4)), 1.0, tmp_path / "out")
    # the NaN of job 4 would be written at release 5 (LET)
    assert "DeviceFault: task 'ctl', cycle 5: dev.u[0] (c0): command nan is not finite" in str(caught.value)
    assert "computed by the step of cycle 4, due at this release" in str(caught.value)
    log = read_log(tmp_path / "dev.log")
    assert writes(log) == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert_ends_safe(log)


def test_a_non_finite_command_in_simulation_too(tmp_path: Path) -> None:
    with pytest.raises(TaskFailed, match=r"cycle 4: dev.u\[0\] \(c0\): command nan"):
        rtloop.simulate(echo_app(tmp_path, "dev_sim_nan", io="immediate", echo=Echo(nan_at=4)), 1.0, tmp_path / "o")


def test_an_e_stop_stops_the_app_in_order_safe_values_first(tmp_path: Path) -> None:
    app = App(unique_name("dev_stop_estop"))
    ctl = app.add_task("ctl", Echo(), period_ns=PERIOD_NS)
    app.add_task("other", Echo(), period_ns=PERIOD_NS)
    dev = app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(tmp_path / "dev.log"),
                         fail_in="estop", limits={"c0": LIMIT})
    app.connect(ctl.y[0], dev.u[0])
    app.connect(dev.y[0], ctl.u[0])
    summary = rtloop.run(app, 30.0, tmp_path / "out")
    assert "E-stop: falling edge on line 'estop' of device 'dev'" in summary.stopped_by and summary.failure is None
    # the summary says when the edge came and when the task's devices were safe after it
    note = next(n for n in summary.notes if n.startswith("E-stop: edge at"))
    edge_ns, safe_ns = map(int, re.search(r"edge at (\d+) ns.*safe at (\d+) ns", note).groups())
    assert 0 < edge_ns < safe_ns, note
    log = read_log(tmp_path / "dev.log")
    assert writes(log) == [0.0, 1.0, 2.0, 3.0]
    assert_ends_safe(log)


def test_max_consecutive_misses(tmp_path: Path) -> None:
    app = echo_app(tmp_path, "dev_stop_misses", echo=Echo(slow_s=0.005), max_consecutive_misses=3)
    with pytest.raises(TaskFailed, match="3 deadline misses in a row"):
        rtloop.run(app, 5.0, tmp_path / "out")
    assert_ends_safe(read_log(tmp_path / "dev.log"))


@pytest.mark.slow
def test_the_watchdog_breaks_a_stuck_step_and_the_device_gets_its_safe_value(tmp_path: Path) -> None:
    # SCHED_OTHER: a step spinning at SCHED_FIFO takes a core from everything else on a shared
    # machine (the supervisor whose watchdog must break it included) for as long as it spins
    app = echo_app(tmp_path, "dev_stop_watchdog", echo=Echo(stuck_at=3), watchdog_periods=1, policy="other")
    with pytest.raises(TaskFailed, match="watchdog"):
        rtloop.run(app, 60.0, tmp_path / "out", limits=Limits(watchdog_min_s=0.5, watchdog_grace_s=1.0))
    log = read_log(tmp_path / "dev.log")
    assert_ends_safe(log)
    # each release wrote what the job before computed, up to the stuck job (the 4th, unless
    # the loaded machine skipped a release before it: SCHED_OTHER)
    assert 1 <= len(writes(log)) <= 4 and writes(log) == [float(k) for k in range(len(writes(log)))]


def _cli_run(tmp_path: Path, name: str) -> subprocess.Popen[str]:
    app_file = tmp_path / "app.toml"
    app_file.write_text(f"""
name = "{unique_name(name)}"
[tasks.ctl]
runnable = "device_test_drivers:Echo"
period_ns = {PERIOD_NS}
[devices.dev]
kind = "device_test_drivers:LogDevice"
task = "ctl"
log = "{tmp_path / 'dev.log'}"
limits.c0 = {{min = -1e6, max = 1e6, safe = -7.0}}
[[connect]]
from = "ctl.y[0]"
to = "dev.u[0]"
[[connect]]
from = "dev.y[0]"
to = "ctl.u[0]"
""")
    return subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app_file), "--out", str(tmp_path / "out"),
                             "--quiet"], cwd=TESTS, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_writes(tmp_path: Path, process: subprocess.Popen[str], count: int = 5) -> None:
    deadline = time.monotonic() + 30
    while len(writes(read_log(tmp_path / "dev.log"))) < count:
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "the device was never written"
        time.sleep(0.05)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_and_sigterm(tmp_path: Path, signum: int) -> None:
    process = _cli_run(tmp_path, f"dev_stop_sig{int(signum)}")
    _wait_for_writes(tmp_path, process)
    process.send_signal(signum)
    _out, err = process.communicate(timeout=30)
    assert process.returncode == 0, err
    assert_ends_safe(read_log(tmp_path / "dev.log"))


def test_kill_9_of_the_supervisor(tmp_path: Path) -> None:
    """The task process outlives a killed supervisor only long enough to make its devices safe
    (the kernel sends it SIGTERM when its parent dies)."""
    process = _cli_run(tmp_path, "dev_stop_kill_sup")
    _wait_for_writes(tmp_path, process)
    process.kill()
    process.communicate(timeout=30)
    deadline = time.monotonic() + 10
    while read_log(tmp_path / "dev.log")[-1:] != ["close"] and time.monotonic() < deadline:
        time.sleep(0.05)
    assert_ends_safe(read_log(tmp_path / "dev.log"))


def test_kill_9_of_the_task_the_supervisor_writes_the_safe_values(tmp_path: Path) -> None:
    """Nothing runs in a task killed with SIGKILL: the supervisor writes its devices' safe values
    from outside (a CAN driver sends the safe frames, a GPIO driver drives the lines) and says so."""
    import json
    import os

    process = _cli_run(tmp_path, "dev_stop_kill_task")
    _wait_for_writes(tmp_path, process)
    os.kill(int((tmp_path / "dev.log.pid").read_text()), signal.SIGKILL)
    _out, err = process.communicate(timeout=60)
    assert process.returncode != 0 and "killed by SIGKILL" in err, err
    log = read_log(tmp_path / "dev.log")
    assert log[-1] == "safe from the supervisor -7.0", log[-5:]
    assert "close" not in log  # the task itself never got to its safe values
    notes = json.loads((tmp_path / "out" / "summary.json").read_text())["notes"]
    assert any(note.startswith("task ctl was killed by SIGKILL before its device 'dev'") and
               note.endswith("the supervisor logged the safe values") for note in notes), notes


# --- a device that cannot be used: exit 2, nothing started ---------------------------------------------

def test_a_device_that_fails_its_configure_is_bad_input_and_nothing_runs(tmp_path: Path) -> None:
    app = App(unique_name("dev_configure_fails"))
    ctl = app.add_task("ctl", Echo(), period_ns=PERIOD_NS)
    app.add_task("other", Echo(), period_ns=PERIOD_NS)
    dev = app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(tmp_path / "dev.log"),
                         fail_in="configure", limits={"c0": LIMIT})
    app.connect(ctl.y[0], dev.u[0])
    with pytest.raises(DeviceError, match=r"devices\.dev\.fail_in: the device did not answer") as caught:
        rtloop.run(app, 1.0, tmp_path / "out")
    assert not isinstance(caught.value, TaskFailed)
    assert read_log(tmp_path / "dev.log") == ["configure", "close"]


def test_a_device_that_fails_its_check_stops_everything_before_it_starts(tmp_path: Path) -> None:
    app = App(unique_name("dev_check_fails"))
    app.add_task("ctl", Echo(), period_ns=PERIOD_NS)
    app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(tmp_path / "no" / "dev.log"),
                   limits={"c0": LIMIT})
    with pytest.raises(DeviceError, match=r"<python>: devices\.dev\.log: its folder does not exist"):
        rtloop.run(app, 1.0, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_simulate_needs_a_twin_for_every_device(tmp_path: Path) -> None:
    app = App(unique_name("dev_no_twin"))
    app.add_task("ctl", Echo(), period_ns=PERIOD_NS)
    app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log="x", limits={"c0": LIMIT})
    with pytest.raises(DeviceError, match=r"devices\.dev\.twin: missing"):
        rtloop.simulate(app, 1.0, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_hardware_run_replays_without_the_hardware(tmp_path: Path) -> None:
    """The device's readings are recorded (the task inputs they feed); rtloop replay plays them back in
    its place, so the replay equals the run even with a twin that answers differently (here: gain 3)."""
    from rtloop.runtime.replay import replay

    rtloop.run(echo_app(tmp_path, "dev_replay", gain=0.5), 0.2, tmp_path / "run")
    result = replay(tmp_path / "run", tmp_path / "replay", echo_app(tmp_path / "unused", "dev_replay", gain=3.0))
    assert result.rows_compared > 10
    assert result.equal, result.divergence.describe() if result.divergence else result.cannot
    simulated = tmp_path / "sim"
    rtloop.simulate(echo_app(tmp_path / "unused", "dev_replay_sim", gain=3.0), 0.2, simulated)
    assert signals(simulated)[3] != signals(tmp_path / "run")[3]  # the gain-3 twin alone would not reproduce it


def test_the_run_equals_simulation_window_ends_before_a_devices_first_stale_read(tmp_path: Path) -> None:
    """first_miss_s: a cycle that read a device's stale values (summary.json devices) ends the window
    like a deadline miss, at the release before it; the earlier of the two wins."""
    import json

    period_ns, t0_ns = 1_000_000, 5_000_000_000
    rows = ["task,cycle,release_ns,start_ns,end_ns"] + [
        f"ctl,{k},{t0_ns + k * period_ns},{t0_ns + k * period_ns + 1000},"
        f"{t0_ns + k * period_ns + (3 * period_ns if k == 8 else 2000)}" for k in range(10)]  # cycle 8 ends late
    (tmp_path / "timing.csv").write_text("\n".join(rows) + "\n")

    def window_with(stale_cycles: list[int]) -> float | None:
        device = {"task": "ctl", "kind": "can", "stale_reads": len(stale_cycles), "first_stale_cycles": stale_cycles}
        summary = {"tasks": {"ctl": {"period_ns": period_ns}}, "devices": {"drive": device}}
        (tmp_path / "summary.json").write_text(json.dumps(summary))
        return first_miss_s(tmp_path)

    assert window_with([]) == 8 * period_ns / 1e9  # the late cycle alone
    assert window_with([5, 6]) == 4 * period_ns / 1e9  # cycle 5's readings were old: equal up to cycle 4
    assert window_with([9]) == 8 * period_ns / 1e9
