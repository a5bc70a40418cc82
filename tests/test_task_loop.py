"""The task process around its loop: a prompt stop, a quiet end, ordered epoch words, bounded catch-up."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import rtloop
from conftest import other_cpu, scaled_ns, unique_name, wait_for_app
from rtloop.ipc.status import STATUS_WORDS, StatusWord, TaskState, WordBlock

P = 1_000_000


HOUR_NS = 3_600_000_000_000  # the longest period a task may have


def _long_period_app(tmp_path: Path, name: str) -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(
        f'name = "{name}"\n'
        "[tasks.slow]\n"
        'runnable = "rt_test_runnables:Counter"\n'
        f"period_ns = {HOUR_NS}\npriority = 70\ncpu = {other_cpu()}\n"
    )
    return path


def _status_of(name: str, task: str, process: subprocess.Popen) -> WordBlock:
    app = wait_for_app(name, process)
    return WordBlock(app.segment(app.registry["tasks"][task]), 0, STATUS_WORDS)


def _wait_until_sleeping_in_its_loop(status: WordBlock, process: subprocess.Popen) -> None:
    """Until the task has run its first cycle (at T0) and sleeps towards T0 + 1 hour."""
    deadline = time.monotonic() + 60
    while status[StatusWord.STATE] != TaskState.RUNNING or status[StatusWord.EXEC_LAST_NS] == 0:
        assert process.poll() is None, process.communicate()[1]
        assert time.monotonic() < deadline, "the task did not start"
        time.sleep(0.05)


@pytest.mark.rt
@pytest.mark.parametrize("stop_by", ["sigint_to_rtloop_run", "sigterm_to_the_task"])
def test_a_task_with_a_one_hour_period_stops_when_asked(tmp_path: Path, rtloop_env, hot_path, stop_by: str) -> None:
    """Both sleeps look at the stop flag while they sleep; they used to sleep the period out
    (a 20 s period took 19.5 s to stop). With a one-hour period, a stop that waited for the next
    release would outlast the test's timeout: ending at all is the proof, whatever the load."""
    name = unique_name(f"stop1h_{hot_path}_{stop_by[:6]}")
    process = subprocess.Popen(
        [sys.executable, "-m", "rtloop.cli", "run", str(_long_period_app(tmp_path, name)), "--out",
         str(tmp_path / "out"), "--quiet"],
        env=rtloop_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        status = _status_of(name, "slow", process)
        _wait_until_sleeping_in_its_loop(status, process)
        if stop_by == "sigint_to_rtloop_run":
            process.send_signal(signal.SIGINT)
        else:
            os.kill(status[StatusWord.PID], signal.SIGTERM)
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 0, stderr
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["stopped_by"] == "signal" and summary["tasks"]["slow"]["cycles"] == 1, summary
    assert summary["elapsed_s"] < HOUR_NS / 1e9, "it stopped before its second release"


def _misses_in_the_last_cycles(timing_csv: Path, period_ns: int, cycles: int, last: int) -> dict[str, int]:
    """Per task: cycles among the last ``last`` that ended after their deadline or were skipped."""
    rows: dict[str, dict[int, tuple[int, int]]] = {}
    with open(timing_csv, newline="") as file:
        for row in csv.DictReader(file):
            rows.setdefault(row["task"], {})[int(row["cycle"])] = (int(row["release_ns"]), int(row["end_ns"]))
    misses = {}
    for task, by_cycle in rows.items():
        window = range(cycles - last, cycles)
        misses[task] = sum(1 for k in window if k not in by_cycle or by_cycle[k][1] - by_cycle[k][0] > period_ns)
    return misses


@pytest.mark.rt
def test_a_task_leaves_sched_fifo_before_its_teardown(tmp_path: Path) -> None:
    """gc, postrun and reporting after the loop ran at the task's SCHED_FIFO priority and delayed
    the last cycles of lower-priority tasks on the same core."""
    from rt_test_runnables import PolicyAfterLoop

    app = rtloop.App(f"leave_fifo_{os.getpid()}")
    policy_file = tmp_path / "policy"
    task = app.add_task("task", PolicyAfterLoop(str(policy_file)), period_ns=P, priority=70, cpu=other_cpu())
    app.record(task.y)
    rtloop.run(app, 0.2, tmp_path / "out")
    with open(tmp_path / "out" / "signals.csv", newline="") as file:
        in_loop = {float(row[-1]) for row in list(csv.reader(file))[2:]}
    assert in_loop == {float(os.SCHED_FIFO)}
    assert int(policy_file.read_text()) == os.SCHED_OTHER


def _jiwy_on_one_core(name: str, period_ns: int) -> rtloop.App:
    """examples/jiwy: controller (priority 80) and plant (81) at 1 kHz on one core, wired both ways."""
    from jiwy_models import JiwyController, JiwyPlant

    app = rtloop.App(name)
    controller = app.add_task("controller", JiwyController(), period_ns=period_ns, priority=80, cpu=other_cpu())
    plant = app.add_task("plant", JiwyPlant(), period_ns=period_ns, priority=81, cpu=other_cpu())
    # (priority 80 and 81 as in the example; other test apps on this shared machine use them too)
    app.connect(plant.y[0:2], controller.u[0:2])
    app.connect(controller.y[0:2], plant.u[0:2])
    app.record(plant.y, controller.y)
    return app


@pytest.mark.rt
@pytest.mark.slow
# Stretched periods (the emulated guest) change the models' dynamics, which this test does not
# look at: only when each task's last cycles ran.
@pytest.mark.filterwarnings("ignore::rtloop.models.base.StepSizeWarning")
def test_jiwy_on_one_core_ends_without_a_phantom_miss(tmp_path: Path) -> None:
    """The higher-priority task leaves SCHED_FIFO when its loop ends, so its teardown (gc, postrun,
    reporting) no longer delays the other task's last cycles (it used to, by 8-9 ms, in every run)."""
    # The end of a run looks the same in a run of any length, and each run costs two task
    # processes' start-up (~1 s): 6 runs of 0.25 s here, the issue's 20 runs of 2 s with
    # RTLOOP_LONG_TESTS=1. Before the fix every run had the phantom.
    long = os.environ.get("RTLOOP_LONG_TESTS") == "1"
    runs, duration_s, last = (20, 2.0, 10) if long else (6, 0.25, 10)
    cycles = round(duration_s * 1e9) // P
    period_ns = scaled_ns(P)  # the same cycles, stretched where Python runs slower (the emulated guest)
    late_runs, phantom_runs = [], []
    for index in range(runs):
        app = _jiwy_on_one_core(f"jiwy_end_{os.getpid()}", period_ns)
        out = tmp_path / f"run{index}"
        rtloop.run(app, cycles * period_ns / 1e9, out)
        misses = _misses_in_the_last_cycles(out / "timing.csv", period_ns, cycles, last)
        if any(misses.values()):
            late_runs.append((index, misses))
        if misses["controller"] and not misses["plant"]:  # the lower-priority task alone was late
            phantom_runs.append((index, misses))
    print(f"runs with a miss in their last {last} cycles: {len(late_runs)} of {runs} {late_runs}")
    # The machine is shared (other apps run SCHED_FIFO tasks on this core too): their noise
    # delays both tasks alike, and now and then one. Before the fix every run had the phantom.
    assert len(phantom_runs) <= 2, f"the lower-priority task alone missed at the end: {phantom_runs}"


def test_the_epoch_is_published_end_first_with_a_fence_and_read_t0_first(monkeypatch) -> None:
    """On aarch64 a task could see T0 with END = 0: the two stores need release / acquire ordering."""
    from rtloop.ipc import segments, status
    from rtloop.ipc.status import ControlWord
    from rtloop.runtime import task

    events: list[tuple[str, int | None]] = []

    class Recorded(dict):
        def __setitem__(self, word, value):
            events.append(("store", int(word)))
            super().__setitem__(word, value)

        def __getitem__(self, word):
            events.append(("load", int(word)))
            return super().get(word, 0)

    monkeypatch.setattr(segments, "fence", lambda: events.append(("fence", None)))
    monkeypatch.setattr(status, "fence", lambda: events.append(("fence", None)), raising=False)
    control = Recorded()
    status.publish_epoch(control, t0_ns=5_000, end_ns=9_000)
    assert events == [("store", ControlWord.END_NS), ("fence", None), ("store", ControlWord.T0_NS)]
    events.clear()
    assert task._wait_for_epoch(control) == (5_000, 9_000)
    loads = [e for e in events if e[0] != "load" or e[1] != ControlWord.STOP]
    assert loads[-3:] == [("load", ControlWord.T0_NS), ("fence", None), ("load", ControlWord.END_NS)]


def test_the_supervisor_publishes_the_epoch_through_the_ordered_store(monkeypatch) -> None:
    from rtloop.runtime import supervisor
    from rtloop.runtime.session import Limits

    published = []
    monkeypatch.setattr(supervisor, "publish_epoch", lambda control, t0_ns, end_ns: published.append((t0_ns, end_ns)))

    class Layout:
        def __init__(self) -> None:
            self.control: dict[int, int] = {}

    class Recorder:
        def start(self, *args) -> None:
            pass

    runner, layout = supervisor.Supervisor.__new__(supervisor.Supervisor), Layout()
    runner.duration_s = 1.0
    runner.limits = Limits()
    runner._start_epoch(layout, Recorder())
    assert published == [(runner.t0_ns, runner.end_ns)] and not layout.control


class _CountingModel:
    n_inputs, n_outputs = 1, 1
    input_names, output_names = ("u",), ("y",)
    step_size_s = None

    def __init__(self) -> None:
        self.steps = 0

    def initialize(self, u, y, t_s) -> None:
        pass

    def calculate(self, u, y) -> None:
        self.steps += 1
        y[0] = self.steps

    def terminate(self, u, y) -> None:
        pass


def test_a_model_catches_up_skipped_releases_a_bounded_number_of_steps_per_cycle(capsys) -> None:
    """Ten skipped releases used to cost eleven model steps in one cycle: the spiral skip exists to stop."""
    from rtloop.models.base import MAX_CATCH_UP_STEPS_PER_CYCLE, ModelRunnable
    from rtloop.runnable import TickInfo

    model = _CountingModel()
    runnable = ModelRunnable(model)
    runnable.tick = TickInfo(cycle=-1, period_ns=P)
    runnable.prerun()
    u, y = np.zeros(1), np.zeros(1)
    steps_per_cycle = []
    for cycle in [0, 1, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25]:  # releases 2..11 skipped
        runnable.tick.cycle = cycle
        before = model.steps
        runnable.step(u, y)
        steps_per_cycle.append(model.steps - before)
    assert max(steps_per_cycle) == 1 + MAX_CATCH_UP_STEPS_PER_CYCLE
    assert model.steps == 26, "the model still follows the release timeline (once caught up)"
    assert runnable.catch_up_steps == 10
    runnable.postrun()
    assert capsys.readouterr().err == ""  # the supervisor says it, once per run, with the true cause


def test_a_live_port_read_that_keeps_failing_leaves_u_untouched() -> None:
    """The Python twin copied straight into u and kept a torn copy after its retries (C uses scratch)."""
    from rtloop.ipc.channels import LatestValue
    from rtloop.ipc.segments import Segment, new_run_token

    segment = Segment.create("torn", os.getpid(), new_run_token(), "port", LatestValue.size_bytes(3))
    try:
        port = LatestValue.initialise(segment, np.array([1.0, 2.0, 3.0]))

        class AlwaysBeingRewritten:
            """Each look at the sequence finds a new even number: every copy is suspect."""

            def __init__(self, words) -> None:
                self.words, self.seq = words, 0

            def __getitem__(self, index):
                if index == 0:
                    self.seq += 2
                    return self.seq
                return self.words[index]

            def __setitem__(self, index, value) -> None:
                self.words[index] = value

        port.words = AlwaysBeingRewritten(port.words)
        u = np.full(3, 9.0)
        assert port.read_into(u) is False
        assert u.tolist() == [9.0, 9.0, 9.0]
        del port
    finally:
        segment.close()
        segment.unlink()
