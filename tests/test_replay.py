"""Replay of a whole run: the read log (stale reads), the real timeline, divergence reports."""

from __future__ import annotations

import csv
import json
import os
import pickle
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import rtloop
from conftest import other_cpu, scaled_ns, scaled_s, skip_in_rtkernel_guest, slowdown
from loaded_runs import JIWY_ON_ONE_CPU, stress_ng
from replay_helpers import pi_loop_app
from rtloop import App
from rtloop.ipc import hotpath
from rtloop.ipc.channels import NO_STAMP, LetChannel
from rtloop.ipc.ring import Int64Ring
from rtloop.ipc.schema import task_segment_size
from rtloop.ipc.segments import Segment, new_run_token
from rtloop.ipc.status import CONTROL_WORDS, STATUS_WORDS, StatusWord, WordBlock
from rtloop.ipc.wiring import READ_LOG_WIDTH, InputLink, TaskWiring, TaskWiringPlan
from rtloop.runnable import TickInfo

P = 1_000_000
T0 = 5_000_000_000
HOG_LOAD_PERCENT = 20
JIWY = Path(__file__).resolve().parent.parent / "examples" / "jiwy"
LONG_TESTS_ENV = "RTLOOP_LONG_TESTS"


def _stale_reads_logged(kind: str, monkeypatch) -> tuple[list[list[int]], list[float], int]:
    """A reader of two writers (P and 2P) whose first writer falls behind: what its read log holds."""
    if kind == "python":
        monkeypatch.setenv(hotpath.PURE_PYTHON_ENV, "1")
    else:
        monkeypatch.delenv(hotpath.PURE_PYTHON_ENV, raising=False)
    token, pid = new_run_token(), os.getpid()
    made: list[Segment] = []
    try:
        fast, slow = (Segment.create("readlog", pid, token, name, LetChannel.size_bytes(2, 4)) for name in "ab")
        log = Segment.create("readlog", pid, token, "reads", Int64Ring.size_bytes(16, READ_LOG_WIDTH))
        control = Segment.create("readlog", pid, token, "control", CONTROL_WORDS * 8)
        task = Segment.create("readlog", pid, token, "task", task_segment_size(16))
        made += [fast, slow, log, control, task]
        writers = [LetChannel.initialise(fast, 2, 4), LetChannel.initialise(slow, 2, 4)]
        Int64Ring.initialise(log, 16, READ_LOG_WIDTH)
        status = WordBlock(task, 0, STATUS_WORDS)
        timing = Int64Ring.initialise(task, 16, 4, STATUS_WORDS * 8)
        plan = TaskWiringPlan(
            inputs=(InputLink(fast.name, slice(0, 2), slice(0, 2), P, "fast"),
                    InputLink(slow.name, slice(1, 2), slice(2, 3), 2 * P, "slow")),
            read_log=log.name, segments=(fast.name, slow.name, log.name))
        assert plan.writers() == ["fast", "slow"]
        wiring = TaskWiring(plan, np.zeros(3), np.zeros(0), status)
        wiring.t0_ns = T0
        work = hotpath.cycle_work(TickInfo(), wiring, WordBlock(control, 0, CONTROL_WORDS), status, timing, P, False)
        assert isinstance(work, hotpath.PythonCycle) == (kind == "python")
        try:
            work.start(T0, T0 + 100 * P, 0)
            writers[0].publish(T0, np.array([1.0, 10.0]))
            writers[1].publish(T0, np.array([2.0, 20.0]))
            work.read_inputs(T0)  # clean: both samples stamped T0 are due
            writers[0].publish(T0 + P, np.array([1.1, 11.0]))
            work.read_inputs(T0 + P)  # clean: the slow writer's T0 sample is due until 2P
            work.read_inputs(T0 + 2 * P)  # both late: fast got P (due 2P), slow got T0 (due 2P)
            writers[0].publish(T0 + 2 * P, np.array([1.2, 12.0]))
            writers[0].publish(T0 + 3 * P, np.array([1.3, 13.0]))
            writers[1].publish(T0 + 2 * P, np.array([2.2, 22.0]))
            work.read_inputs(T0 + 3 * P)  # clean again
            records = Int64Ring(log).drain().tolist()
            return records, wiring.u.tolist(), status[StatusWord.STALE_READS]
        finally:
            work.close()
    finally:
        for segment in made:
            segment.unlink()


def test_a_clean_cycle_logs_nothing_a_stale_read_logs_what_it_got_identically_in_c_and_python(monkeypatch) -> None:
    kinds = ["python", "c"] if hotpath.c_built() else ["python"]
    results = {kind: _stale_reads_logged(kind, monkeypatch) for kind in kinds}
    records, u, stale = results["python"]
    assert records == [[2 * P, 0, P, 2 * P], [2 * P, 1, 0, 2 * P]]
    assert u == [1.3, 13.0, 22.0] and stale == 2
    assert len(set(map(repr, results.values()))) == 1, results


def test_a_read_that_found_no_sample_logs_no_stamp(monkeypatch) -> None:
    monkeypatch.setenv(hotpath.PURE_PYTHON_ENV, "1")
    token, pid = new_run_token(), os.getpid()
    made = [Segment.create("readlog0", pid, token, "a", LetChannel.size_bytes(1, 2)),
            Segment.create("readlog0", pid, token, "reads", Int64Ring.size_bytes(4, READ_LOG_WIDTH))]
    try:
        LetChannel.initialise(made[0], 1, 2)
        Int64Ring.initialise(made[1], 4, READ_LOG_WIDTH)
        plan = TaskWiringPlan(inputs=(InputLink(made[0].name, slice(0, 1), slice(0, 1), P, "a"),),
                              read_log=made[1].name, segments=(made[0].name, made[1].name))
        wiring = TaskWiring(plan, np.zeros(1), np.zeros(0), None)
        wiring.t0_ns = T0
        wiring.read_inputs(T0 + 3 * P, wiring.u)
        assert Int64Ring(made[1]).drain().tolist() == [[3 * P, 0, NO_STAMP, 3 * P]]
    finally:
        for segment in made:
            segment.unlink()


# --- whole runs, replayed ---------------------------------------------------------------------------

JIWY_APP = JIWY_ON_ONE_CPU + """[ports.setpoint]
to = "controller.u[2:4]"
[record]
signals = ["plant.y", "controller.y", "controller.u"]
"""


def _rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as file:
        return list(csv.reader(file))


def _faults(run_dir: Path) -> tuple[int, int]:
    """(deadline misses, stale reads) of a run, from its summary and reads.csv."""
    summary = json.loads((run_dir / "summary.json").read_text())
    misses = sum(task["deadline_misses"] for task in summary["tasks"].values())
    return misses, len(_rows(run_dir / "reads.csv")) - 1


def _replay_cli(run_dir: Path, out: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rtloop.cli", "replay", str(run_dir), "--out", str(out)],
                          env=env, capture_output=True, text=True, timeout=600)


def _lets_own_simulation_differs(app_file: Path, run_dir: Path, tmp_path: Path, env: dict[str, str]) -> bool:
    """Whether plain simulation (the logical timeline, the run's port inputs) differs from the run:
    then the run's timing faults changed its signals, and a replay that equals it followed them."""
    code = ("import sys; from pathlib import Path; from rtloop.app.appfile import load_app; "
            "from rtloop.runtime.replay import port_writes; from rtloop.runtime.simulate import simulate; "
            "import json; run = Path(sys.argv[2]); d = json.loads((run / 'summary.json').read_text())['elapsed_s']; "
            "simulate(load_app(sys.argv[1]), round(d, 3), sys.argv[3], port_writes=port_writes(run))")
    subprocess.run([sys.executable, "-c", code, str(app_file), str(run_dir), str(tmp_path / "let")], env=env,
                   check=True, capture_output=True, timeout=600)
    return _rows(tmp_path / "let" / "signals.csv")[:len(_rows(run_dir / "signals.csv"))] != _rows(
        run_dir / "signals.csv")


@pytest.mark.alone
@pytest.mark.rt
@pytest.mark.timeout(300)
@pytest.mark.skipif(shutil.which("stress-ng") is None, reason="stress-ng is not installed (apt install stress-ng)")
def test_a_loaded_jiwy_run_with_live_setpoints_replays_bit_for_bit_misses_and_stale_reads_included(
        tmp_path: Path, rtloop_env) -> None:
    from conftest import other_cpu, wait_for_cycles
    from rtloop.ipc.ports import connect_app

    cpu = other_cpu()
    name = f"replay_jiwy_{os.getpid()}"
    app_file = tmp_path / f"{name}.toml"
    app_file.write_text(JIWY_APP.format(name=name, cpu=cpu))
    run_dir = tmp_path / "run"
    # Two CPU hogs on the tasks' core, real-time above them but busy only part of the time: the
    # tasks are held off in bursts, so they miss deadlines and read samples their writer had
    # not yet published. Only this process group is stopped afterwards, when the run has ended (its
    # timeout is a bound past the run's, whose start takes seconds on a loaded machine).
    with stress_ng("--cpu", "2", "--cpu-load", str(HOG_LOAD_PERCENT), "--taskset", str(cpu),
                   "--sched", "fifo", "--sched-prio", "90", "--timeout", "200s"):
        process = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", "6",
                                    "--out", str(run_dir), "-q"], env=rtloop_env,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            app = connect_app(name, timeout_s=60)
            wait_for_cycles(app, "controller", 1, process)  # the run is under way (start-up may take long)
            for step in range(8):  # a new setpoint every 0.6 s, the first at about 1 s, the last at 5.2 s of 6
                time.sleep(0.6 if step else 1.0)
                app.write("setpoint", [0.4 * (-1) ** step, 0.1 * (step % 3)])
        finally:
            _out, err = process.communicate(timeout=120)
    assert process.returncode == 0, err
    misses, stale = _faults(run_dir)
    assert misses and stale, f"the run had {misses} misses and {stale} stale reads: nothing to prove"
    assert len(_rows(run_dir / "inputs.csv")) - 1 >= 5, "the setpoints entered the run"
    replayed = _replay_cli(run_dir, tmp_path / "replay", rtloop_env)
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr
    assert "equal bit for bit over the whole run" in replayed.stdout
    run_rows, replay_rows = _rows(run_dir / "signals.csv"), _rows(tmp_path / "replay" / "signals.csv")
    assert run_rows == replay_rows and len(run_rows) > 1000
    assert _lets_own_simulation_differs(app_file, run_dir, tmp_path, rtloop_env), (
        "the faults did not change the signals: the test proved nothing beyond simulation")


def _slow_step_app(name: str, overrun: str, profile: Path) -> App:
    """A PI controller and a plant whose step takes 2.5 periods longer every 50th cycle (1 kHz here,
    stretched with its slow step where Python is slower: the emulated guest)."""
    from rt_test_runnables import PiController, SlowIntegrator

    app = App(name)
    controller = app.add_task("controller", PiController(2), period_ns=scaled_ns(P), cpu=other_cpu())
    plant = app.add_task("plant", SlowIntegrator(2, slow_s=scaled_s(0.0025), every=50), period_ns=scaled_ns(P),
                         cpu=other_cpu(), priority=81, overrun=overrun)
    app.connect(plant.y, controller.u[0:2])
    app.connect(controller.y, plant.u)
    app.port("setpoint", to=controller.u[2:4], feed=profile)
    app.record(plant.y, controller.y, controller.u)
    return app


@pytest.mark.rt
@pytest.mark.timeout(240 if slowdown() == 1 else 900)
@pytest.mark.parametrize("overrun", ["skip", "catch_up"])
def test_a_run_with_a_slow_step_every_50th_cycle_replays_bit_for_bit(overrun: str, tmp_path: Path,
                                                                     hot_path: str) -> None:
    from rtloop.runtime.replay import replay

    profile = tmp_path / "setpoints.csv"
    stretch = slowdown()
    profile.write_text(f"t_s,pan,tilt\n0,0.5,-0.25\n{0.35 * stretch},-0.3,0.4\n{0.8 * stretch},0.1,0.0\n")
    name = f"replay_slow_{overrun[0]}{hot_path[0]}_{os.getpid()}"
    # 25 slow steps in 1.25 s (as many as every 100th cycle gave in 2.5 s: the same faults in half the time)
    summary = rtloop.run(_slow_step_app(name, overrun, profile), scaled_s(1.25), tmp_path / "run")
    plant = summary.tasks["plant"]
    assert plant.timing.deadline_misses >= 20, "a slow step every 50th cycle overruns"
    if overrun == "skip":
        assert plant.timing.overruns >= 40, "each slow step skips about two releases"
    else:  # every release runs, late: the controller reads samples the plant has not published yet
        assert summary.tasks["controller"].stale_reads >= 20
    result = replay(tmp_path / "run", tmp_path / "replay", app=_slow_step_app(name, overrun, profile))
    assert result.cannot is None and result.divergence is None, result
    assert result.equal and result.rows_compared == result.rows_in_run > 100  # fewer when the machine is loaded
    assert _rows(tmp_path / "run" / "signals.csv") == _rows(tmp_path / "replay" / "signals.csv")
    lets = rtloop.simulate(_slow_step_app(name, overrun, profile), scaled_s(1.25), tmp_path / "let")
    assert lets.tasks["plant"].timing.overruns == 0
    assert _rows(tmp_path / "let" / "signals.csv") != _rows(tmp_path / "run" / "signals.csv"), (
        "the overruns changed the signals (else this test proves nothing beyond simulation)")


class Noisy(rtloop.Runnable):
    """Not deterministic: its output depends on a random draw (what a replay cannot reproduce)."""

    n_inputs, n_outputs = 2, 2

    def step(self, u, y) -> None:
        y[:] = u + np.random.default_rng().random()


def _edit(path: Path, row: int, column: int, value: str) -> None:
    rows = _rows(path)
    rows[row][column] = value
    path.write_text("".join(",".join(cells) + "\n" for cells in rows))


def test_a_difference_is_reported_with_its_cycle_task_values_and_inputs(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    writes = {("controller", 30): [("setpoint", [1.0, -1.0])]}
    rtloop.simulate(pi_loop_app("replay_div"), 0.2, tmp_path / "run", port_writes=writes)
    (tmp_path / "run" / "inputs.csv").write_text("task,cycle,port,values\ncontroller,30,setpoint,1.0 -1.0\n")
    result = replay(tmp_path / "run", tmp_path / "same", app=pi_loop_app("replay_div"))
    assert result.equal and result.rows_compared == result.rows_in_run == 201 and result.port_inputs == 1
    _edit(tmp_path / "run" / "signals.csv", 101, 1, "0.125")  # plant.y[0] at t = 0.1 s: plant cycle 49
    result = replay(tmp_path / "run", tmp_path / "diff", app=pi_loop_app("replay_div"))
    assert not result.equal and result.rows_compared == 100
    divergence = result.divergence
    assert (divergence.t_s, divergence.task, divergence.cycle) == (0.1, "plant", 49)
    assert divergence.signals[0][:2] == ("plant.y[0]", "0.125") and len(divergence.signals) == 1
    assert divergence.inputs is not None and len(divergence.inputs) == 2 and divergence.inputs[0] != 0.0
    assert "not deterministic" in divergence.describe()


def test_a_model_that_is_not_deterministic_diverges_and_says_where(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    rtloop.simulate(pi_loop_app("replay_noisy", Noisy()), 0.05, tmp_path / "run")
    result = replay(tmp_path / "run", tmp_path / "replay", app=pi_loop_app("replay_noisy", Noisy()))
    assert not result.equal and result.divergence is not None
    assert (result.divergence.t_s, result.divergence.task, result.divergence.cycle) == (0.002, "plant", 0)


def test_a_lost_timing_record_is_named_never_called_equal(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    rtloop.simulate(pi_loop_app("replay_gap"), 0.1, tmp_path / "run")
    timing = tmp_path / "run" / "timing.csv"
    timing.write_text("".join(line for line in timing.read_text().splitlines(keepends=True)
                              if not line.startswith(("plant,20,", "plant,21,"))))
    result = replay(tmp_path / "run", tmp_path / "replay", app=pi_loop_app("replay_gap"))
    assert not result.equal
    assert result.cannot == ("from t = 0.04 s: timing.csv lacks plant cycles 20..21, which followed a cycle that "
                             "ended in time: the replay cannot know what they did")
    assert result.rows_compared == result.rows_in_run == 40  # every row before it, and equal


def test_a_run_with_no_signal_rows_is_never_called_equal(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    rtloop.simulate(pi_loop_app("replay_empty"), 0.02, tmp_path / "run")
    signals = tmp_path / "run" / "signals.csv"
    signals.write_text(signals.read_text().splitlines(keepends=True)[0])
    result = replay(tmp_path / "run", tmp_path / "replay", app=pi_loop_app("replay_empty"))
    assert not result.equal and "holds no rows" in result.cannot


# --- --keep runs: a window replayed from the snapshots kept at its start -------------------------


def _keep_app(name: str, fmu: Path) -> App:
    """JIWY: the Python PID controller and the plant as an FMU (its state through FMI), one core."""
    from jiwy_models import JiwyController

    from rtloop.models import ModelRunnable
    from rtloop.models.fmu import FmuModel

    app = App(name)
    controller = app.add_task("controller", JiwyController(), period_ns=P, cpu=other_cpu())
    plant = app.add_task("plant", ModelRunnable(FmuModel(fmu)), period_ns=P, priority=81, cpu=other_cpu())
    app.connect(plant.y[0:2], controller.u[0:2])
    app.connect(controller.y[0:2], plant.u[0:2])
    app.port("setpoint", to=controller.u[2:4])
    app.record(plant.y, controller.y, controller.u)
    return app


@pytest.fixture(scope="module")
def jiwy_fmu(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("gcc") is None:
        pytest.skip("gcc not installed: cannot build the JIWY FMU")
    from rtloop.models.fmu_build import build_fmu

    return build_fmu(JIWY / "models" / "fmu", tmp_path_factory.mktemp("fmu") / "JiwyPlant.fmu")


def _keep_run_replays_its_window(tmp_path: Path, fmu: Path, duration_s: float, keep_s: float) -> None:
    from rtloop.ipc.ports import connect_app
    from rtloop.runtime.replay import replay

    name = f"replay_keep_{os.getpid()}"
    done = threading.Event()

    written = []

    def write_setpoints() -> None:  # live port writes all along, some before the window, some in it
        app = connect_app(name, timeout_s=60)
        step = 0
        while not done.wait(min(0.7, keep_s / 3)):  # several inside the window
            app.write("setpoint", [0.3 * (-1) ** step, 0.05 * (step % 4)])
            written.append(step)
            step += 1

    writer = threading.Thread(target=write_setpoints, daemon=True)
    writer.start()
    try:
        rtloop.run(_keep_app(name, fmu), duration_s, tmp_path / "run", keep_s=keep_s)
    finally:
        done.set()
        writer.join(10)
    snapshots = sorted((tmp_path / "run" / "snapshots").glob("*.pkl"))
    assert snapshots, "a --keep run keeps the task snapshots of its kept segments"
    result = replay(tmp_path / "run", tmp_path / "replay", app=_keep_app(name, fmu))
    assert result.cannot is None and result.divergence is None, (result.cannot, result.divergence)
    assert result.equal and result.from_s > 0, "the files no longer hold the run from t = 0: a window"
    assert duration_s - result.from_s >= keep_s, "the replay covers at least the kept window"
    assert result.rows_compared == result.rows_in_run > 100
    assert result.port_inputs >= 1, "setpoints written inside the window were fed back"
    taken = (tmp_path / "run" / "inputs.csv").read_text().splitlines()[1:]
    assert result.port_inputs <= len(taken) < len(written) - 2, "inputs.csv rotates with the window"


@pytest.mark.rt
@pytest.mark.timeout(400)
@skip_in_rtkernel_guest(
    "JIWY's FMU plant and PID are made for 1 ms steps (stretched to the guest's 20 ms the loop diverged to inf at "
    "cycle 1960), and at 1 ms the emulated tasks skip most releases (4 in 5 under a host load of ~6): the kept "
    "files, pinned around the misses, then still began at t = 0 and no window was left to replay from a snapshot; "
    "the flight recorder and replay do not depend on the kernel")
def test_a_keep_run_replays_its_last_window_python_and_fmu_tasks(tmp_path: Path, jiwy_fmu: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    # 20 segments of a quarter of a second (the recorder's shortest is 1 s; shortened here, the
    # run is the same in every other respect), more than the flight recorder keeps (12 pinned +
    # the window of 0.5 s, its snapshot's segment and the current one): the early ones are gone,
    # so the replay must start from a snapshot
    from rtloop.record import flight

    monkeypatch.setattr(flight, "MIN_SEGMENT_NS", 250_000_000)
    _keep_run_replays_its_window(tmp_path, jiwy_fmu, 5.0, 0.5)


@pytest.mark.rt
@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.skipif(os.environ.get(LONG_TESTS_ENV) != "1", reason=f"a 60 s run: set {LONG_TESTS_ENV}=1 to run it "
                    "(test_a_keep_run_replays_its_last_window_python_and_fmu_tasks is its 5 s variant)")
def test_a_keep_10_run_of_60_s_replays_its_last_window_python_and_fmu_tasks(tmp_path: Path, jiwy_fmu: Path) -> None:
    _keep_run_replays_its_window(tmp_path, jiwy_fmu, 60.0, 10.0)


def test_a_window_whose_task_state_was_not_saved_says_so(tmp_path: Path) -> None:
    from rtloop.runtime.replay import window_start
    from rtloop.runtime.snapshot import SNAPSHOTS_DIR, TaskSnapshot

    folder = tmp_path / SNAPSHOTS_DIR
    folder.mkdir()
    snapshots = [TaskSnapshot("controller", 3 * P, 3, 2, (0.0,) * 4, (0.0,) * 2, b"state"),
                 TaskSnapshot("plant", 3 * P, 3, 2, (0.0,) * 2, (0.0,) * 2, None,
                              "StateNotCaptured: 20-sim-cpp model 'Plant' keeps its state in compiled code")]
    with open(folder / "000004.pkl", "wb") as file:
        pickle.dump(snapshots, file)
    why = window_start(tmp_path, {"controller": [], "plant": []}, {"controller": P, "plant": P}, {})
    assert why == ("the window from t = 0.003 s cannot be replayed: the state of task 'plant' could not be saved "
                   "(StateNotCaptured: 20-sim-cpp model 'Plant' keeps its state in compiled code)")


def test_model_states_are_saved_and_restored_or_refused_with_the_reason(tmp_path: Path, jiwy_fmu: Path) -> None:
    from jiwy_models import JiwyController

    from rtloop.models import ModelRunnable
    from rtloop.models.base import StateNotCaptured
    from rtloop.models.fmu import FmuModel
    from rtloop.runtime.snapshot import restore_state, save_state

    def steps(runnable, n: int, u: np.ndarray) -> list[float]:
        y = np.zeros(runnable.n_outputs)
        out = []
        for k in range(n):
            runnable.tick = TickInfo(cycle=k, period_ns=P)
            runnable.step(u, y)
            out += y.tolist()
        return out

    for make in (JiwyController, lambda: ModelRunnable(FmuModel(jiwy_fmu))):
        first, second = make(), make()
        for runnable in (first, second):
            if hasattr(runnable, "check_period"):
                runnable.check_period(P)
            runnable.prerun()
        u = np.array([0.1, -0.2, 0.3, 0.05][: first.n_inputs])
        steps(first, 50, u)
        state, reason = save_state(first)
        assert state is not None, reason
        expected = steps(first, 30, u)
        restore_state(second, state)
        assert steps(second, 30, u) == expected, type(first).__name__
        first.postrun()
        second.postrun()

    class Opaque:  # what compiled code without a way to read its state out looks like to us
        kind, n_inputs, n_outputs = "20sim-cpp", 1, 1
        input_names = output_names = step_size_s = None
        path = "models/Plant"

        def initialize(self, u, y, t_s) -> None:
            pass

    state, reason = save_state(ModelRunnable(Opaque()))
    assert state is None and reason.startswith("StateNotCaptured: 20sim-cpp model 'models/Plant' keeps its state")
    with pytest.raises(StateNotCaptured):
        ModelRunnable(Opaque()).save_state()
