"""The compiled hot path and its Python twin: same results, bounded reads, lean task processes, fallback."""

from __future__ import annotations

import csv
import gc
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import rtloop
import shm_stress
from conftest import other_cpu, scaled_ns, scaled_s, unique_name, wait_for_app, wait_for_cycles, wait_for_task_pids
from rt_test_runnables import Counter, Gain, Integrator, MatrixProduct, PiController, RaiseAt
from rtloop import App
from rtloop.ipc import hotpath
from rtloop.ipc.channels import LetChannel
from rtloop.ipc.ring import Int64Ring
from rtloop.ipc.schema import task_segment_size
from rtloop.ipc.segments import Segment, new_run_token
from rtloop.ipc.status import CONTROL_WORDS, STATUS_WORDS, StatusWord, WordBlock
from rtloop.ipc.wiring import InputLink, TaskWiring, TaskWiringPlan
from rtloop.runnable import TickInfo

P = 1_000_000
SRC = Path(__file__).resolve().parent.parent / "src"
needs_c = pytest.mark.skipif(not hotpath.c_built(), reason=f"the C hot path is not built: {hotpath.why_python()}")


def rows_of(path: Path) -> list[list[str]]:
    with open(path, newline="") as file:
        return list(csv.reader(file))


def every_feature_app(profile: Path) -> App:
    """Connections (two from one writer, one multi-rate), a profile, a live port, an output port."""
    app = App(unique_name("hotpath_all"))
    controller = app.add_task("controller", PiController(2), period_ns=P)
    plant = app.add_task("plant", Integrator(2), period_ns=P)
    monitor = app.add_task("monitor", Gain(4, gain=2.0), period_ns=3 * P)
    clock = app.add_task("clock", Counter(), period_ns=2 * P)
    app.connect(plant.y, controller.u[0:2])
    app.connect(controller.y, plant.u)
    app.connect(plant.y[1], monitor.u[0])  # two connections from one writer, in reverse order
    app.connect(plant.y[0], monitor.u[2])
    app.connect(clock.y[1], monitor.u[1])
    app.port("setpoint", to=controller.u[2:4], feed=profile)
    app.port("trim", to=monitor.u[3], initial=[0.5])
    app.port("angles", source=plant.y)
    app.record(plant.y, controller.y, monitor.y, clock.y, monitor.u)
    return app


@needs_c
def test_c_and_python_simulate_identical_signals_and_timelines(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv(hotpath.PURE_PYTHON_ENV, raising=False)
    profile = tmp_path / "steps.csv"
    profile.write_text("t_s,a,b\n0,0,0\n0.05,1.0,-0.5\n0.13,0.25,2.0\n")
    results = {}
    for kind in ("c", "python"):
        if kind == "python":
            monkeypatch.setenv(hotpath.PURE_PYTHON_ENV, "1")
        writes = {("monitor", 10): [("trim", [1.5])], ("monitor", 40): [("trim", [-2.25])]}  # as a replay does
        summary = rtloop.simulate(every_feature_app(profile), 0.3, tmp_path / kind, port_writes=writes)
        assert summary.hot_path == kind
        timing = [row[:3] for row in rows_of(tmp_path / kind / "timing.csv")]
        results[kind] = (rows_of(tmp_path / kind / "signals.csv"), timing, summary.ports["angles"].sent,
                         {name: task.stale_reads for name, task in summary.tasks.items()},
                         rows_of(tmp_path / kind / "inputs.csv"))
    assert results["c"] == results["python"]
    inputs = results["c"][4]
    assert inputs[1:] == [["monitor", "10", "trim", "1.5"], ["monitor", "40", "trim", "-2.25"]]  # each once
    signals = results["c"][0]
    assert len(signals) > 250 and float(signals[-1][1]) != 0.0  # the loop really moved
    assert results["c"][2] == 300  # one output-port row per plant tick


def _reader_of(channel_segment: Segment, n_values: int, spans: list[tuple[slice, slice]], period_ns: int):
    """A task wiring reading ``spans`` (source, target) of one writer's channel, and its cycle work."""
    token = new_run_token()
    control = Segment.create("hotpath", os.getpid(), token, "control", CONTROL_WORDS * 8)
    task = Segment.create("hotpath", os.getpid(), token, "task", task_segment_size(16))
    status = WordBlock(task, 0, STATUS_WORDS)
    timing = Int64Ring.initialise(task, 16, 4, STATUS_WORDS * 8)
    plan = TaskWiringPlan(
        inputs=tuple(InputLink(channel_segment.name, source, target, period_ns) for source, target in spans),
        segments=(channel_segment.name,),
    )
    u = np.zeros(max(target.stop for _, target in spans))
    wiring = TaskWiring(plan, u, np.zeros(0), status)
    work = hotpath.cycle_work(TickInfo(), wiring, WordBlock(control, 0, CONTROL_WORDS), status, timing, P, False)
    return wiring, work, status, [control, task]


def test_a_replayed_read_takes_the_sample_given_in_place_of_the_channels(hot_path) -> None:
    """``read_inputs(release_ns, instead)``, the replay's stale reads: the given sample (the input's
    scratch layout) goes where the channel's would, None keeps the inputs, and the channel is not read."""
    segment = Segment.create("hotpath", os.getpid(), new_run_token(), "y", LetChannel.size_bytes(3, 2))
    made = [segment]
    try:
        LetChannel.initialise(segment, 3, 2).publish(0, np.array([1.0, 2.0, 3.0]))
        spans = [(slice(2, 3), slice(0, 1)), (slice(0, 2), slice(1, 3))]
        wiring, work, _status, more = _reader_of(segment, 3, spans, P)
        made += more
        work.start(0, 10 * P, 0)
        work.read_inputs(0, {0: np.array([7.0, 8.0, 9.0])})
        assert wiring.u.tolist() == [9.0, 7.0, 8.0]
        work.read_inputs(P, {0: None})  # the run found no sample at all: the inputs keep their values
        assert wiring.u.tolist() == [9.0, 7.0, 8.0] and work.stale_reads == 0
        work.read_inputs(P, None)
        assert wiring.u.tolist() == [3.0, 1.0, 2.0]
        for wrong, error in (({1: None}, ValueError), ({0: np.zeros(2)}, ValueError), ([None], TypeError),
                             ({"0": None}, TypeError)):
            with pytest.raises(error):
                work.read_inputs(P, wrong)  # type: ignore[arg-type]
    finally:
        for made_segment in made:
            made_segment.unlink()


def test_a_writer_stuck_mid_write_costs_one_bounded_stale_read_and_no_torn_input(hot_path) -> None:
    segment = Segment.create("hotpath", os.getpid(), new_run_token(), "y", LetChannel.size_bytes(3, 2))
    made = [segment]
    try:
        channel = LetChannel.initialise(segment, 3, 2)
        channel.publish(0, np.array([1.0, 2.0, 3.0]))
        # two connections from the same writer: y[2] → u[0] and y[0:2] → u[1:3]
        wiring, work, status, more = _reader_of(segment, 3, [(slice(2, 3), slice(0, 1)), (slice(0, 2), slice(1, 3))], P)
        made += more
        work.start(0, 10 * P, 0)
        work.read_inputs(0)
        assert wiring.u.tolist() == [3.0, 1.0, 2.0] and work.stale_reads == 0
        for slot in range(2):  # the writer was preempted mid-write, in every slot: the reader must not spin
            base = 8 + slot * 5
            channel.words[base + 2] = np.float64(99.0).view(np.int64)  # half-written payload
            channel.words[base] |= 1
        # the CPU time this thread spent: a reader that spins spends it, one the loaded machine left
        # waiting for a core does not (a wall-clock bound could not tell the two apart)
        started = time.thread_time()
        work.read_inputs(P)
        assert time.thread_time() - started < 0.5
        assert wiring.u.tolist() == [3.0, 1.0, 2.0], "a torn slot must never reach u"
        assert work.stale_reads == 1 and status[StatusWord.STALE_READS] == 1, "one writer, one read"
    finally:
        for made_segment in made:
            made_segment.unlink()


@needs_c
@pytest.mark.timeout(240)
def test_c_reader_sees_no_torn_value_in_300k_reads_across_cores(monkeypatch) -> None:
    monkeypatch.delenv(hotpath.PURE_PYTHON_ENV, raising=False)
    token = new_run_token()
    segment = Segment.create("stress_c", os.getpid(), token, "let", LetChannel.size_bytes(shm_stress.N_VALUES, 2))
    stop = Segment.create("stress_c", os.getpid(), token, "stop", 8)
    made = [segment, stop]
    import multiprocessing

    try:
        LetChannel.initialise(segment, shm_stress.N_VALUES, 2)
        wiring, work, _status, more = _reader_of(
            segment, shm_stress.N_VALUES, [(slice(0, shm_stress.N_VALUES), slice(0, shm_stress.N_VALUES))], 1)
        made += more
        assert not isinstance(work, hotpath.PythonCycle)
        work.start(0, 2**62, 0)
        writer = multiprocessing.get_context("spawn").Process(target=shm_stress.let_writer,
                                                              args=(segment.name, 0, stop.name))
        writer.start()
        os.sched_setaffinity(0, {1})
        while LetChannel(segment).words[0] < 1000:
            time.sleep(0.001)
        # Each read's inputs are copied into their own row of a block, checked in one numpy
        # operation per 10k reads (only the C reader writes wiring.u, so the copy is the read).
        block = np.zeros((10_000, shm_stress.N_VALUES))
        rows = list(block)
        torn, seen = 0, set()
        for _ in range(30):
            for row in rows:
                work.read_inputs(2**61)
                np.copyto(row, wiring.u)
            torn += int(np.count_nonzero(~shm_stress.consistent_rows(block)))
            seen.update(block[::100, 0].tolist())
        stop.buffer.cast("q")[0] = 1
        writer.join(10)
        assert torn == 0
        assert len(seen) > 100, "the writer should have been writing all along"
    finally:
        os.sched_setaffinity(0, set(range(os.cpu_count() or 1)))
        for made_segment in made:
            made_segment.unlink()


def _status_of(pid: int) -> dict[str, str]:
    lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    return {key: value.strip() for key, _, value in (line.partition(":") for line in lines)}


@pytest.mark.rt
def test_task_processes_run_one_thread_and_lock_less_memory(tmp_path: Path, rtloop_env) -> None:
    name = f"lean_{os.getpid()}"
    app_file = tmp_path / "lean.toml"
    app_file.write_text(
        f'name = "{name}"\n[tasks.counter]\nrunnable = "rt_test_runnables:Counter"\n'
        f"period_ns = {scaled_ns(1_000_000)}\ncpu = {other_cpu()}\n[record]\nsignals = ['counter.y']\n"
    )
    process = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file),
                                "--duration", str(scaled_s(3)), "--out", str(tmp_path / "out")],
                               env=rtloop_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        app = wait_for_app(name, process, scaled_s(60))
        pid = wait_for_task_pids(app, process, scaled_s(60))["counter"]
        wait_for_cycles(app, "counter", 2, process, scaled_s(60))  # prerun done, memory locked
        status = _status_of(pid)
    finally:
        process.communicate(timeout=scaled_s(30))
    assert process.returncode == 0
    assert status["Threads"] == "1", "no BLAS or OpenMP worker threads beside the loop"
    locked_mb = int(status["VmLck"].split()[0]) / 1024
    mapped_mb = int(status["VmSize"].split()[0]) / 1024
    # 148 MB with OpenBLAS's worker pool, 111 MB with one thread and everything locked, 69 MB
    # here now: numpy and its libraries alone are ~39 MB (BENCHMARKS.md, "Memory locked").
    assert 20 < locked_mb < 75, f"VmLck {locked_mb:.0f} MB"
    # OpenBLAS's work buffer (32 MB on x86_64, 16–32 MB on arm64 builds) is mapped but not locked.
    assert mapped_mb - locked_mb > 15, f"VmSize {mapped_mb:.0f} MB, VmLck {locked_mb:.0f} MB"


def _simulate_cli(tmp_path: Path, env: dict[str, str], prelude: str = "") -> subprocess.CompletedProcess:
    app_file = tmp_path / "two.toml"
    app_file.write_text(
        'name = "hotpath_say_once"\n'
        '[tasks.a]\nrunnable = "rt_test_runnables:Counter"\nperiod_ns = 1_000_000\n'
        '[tasks.b]\nrunnable = "rt_test_runnables:Noop"\nperiod_ns = 1_000_000\n'
    )
    code = f"{prelude}import sys; from rtloop.cli.main import main; sys.exit(main())"
    return subprocess.run([sys.executable, "-c", code, "simulate", str(app_file), "--duration", "0.05",
                           "--out", str(tmp_path / "out")], env=env, capture_output=True, text=True, timeout=60)


def test_pure_python_is_said_once_and_written_in_the_summary(tmp_path: Path, rtloop_env) -> None:
    result = _simulate_cli(tmp_path, {**rtloop_env, hotpath.PURE_PYTHON_ENV: "1"})
    assert result.returncode == 0, result.stderr
    said = [line for line in result.stderr.splitlines() if "runs in Python" in line]
    assert said == ["rtloop: per-cycle work runs in Python, not C: RTLOOP_PURE_PYTHON=1"]
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["hot_path"] == "python"


@needs_c
def test_the_compiled_path_is_used_silently_when_built(tmp_path: Path, rtloop_env) -> None:
    env = {k: v for k, v in rtloop_env.items() if k != hotpath.PURE_PYTHON_ENV}
    result = _simulate_cli(tmp_path, env)
    assert result.returncode == 0 and "runs in Python" not in result.stderr
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["hot_path"] == "c"


def test_an_unbuilt_extension_falls_back_to_python_with_one_line(tmp_path: Path, rtloop_env) -> None:
    env = {k: v for k, v in rtloop_env.items() if k != hotpath.PURE_PYTHON_ENV}
    result = _simulate_cli(tmp_path, env, prelude="import sys; sys.modules['rtloop.ipc._hotpath'] = None; ")
    assert result.returncode == 0, result.stderr
    said = [line for line in result.stderr.splitlines() if "runs in Python" in line]
    assert len(said) == 1 and "rtloop.ipc._hotpath is not built" in said[0]
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["hot_path"] == "python"


@pytest.mark.slow
def test_a_build_without_a_compiler_only_warns(tmp_path: Path) -> None:
    root = SRC.parent
    result = subprocess.run(
        [sys.executable, "setup.py", "-q", "build_ext", "--build-lib", str(tmp_path / "lib"),
         "--build-temp", str(tmp_path / "temp")],
        cwd=root, env={**os.environ, "CC": "/bin/false", "LDSHARED": "/bin/false"},
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert "_hotpath" in result.stderr and "building" in result.stderr.lower()
    assert not list((tmp_path / "lib").rglob("_hotpath*.so"))


@needs_c
def test_a_closed_core_holds_no_shared_memory_and_refuses_work(monkeypatch) -> None:
    monkeypatch.delenv(hotpath.PURE_PYTHON_ENV, raising=False)
    writer = Segment.create("hotpath", os.getpid(), new_run_token(), "chan", LetChannel.size_bytes(2, 3))
    LetChannel.initialise(writer, 2, 3)
    _wiring, work, _status, segments = _reader_of(writer, 2, [(slice(0, 2), slice(0, 2))], P)
    work.start(0, P, 0)
    work.close()
    work.close()  # twice is fine
    with pytest.raises(ValueError, match="closed"):
        work.read_inputs(0)
    for segment in [writer, *segments]:
        segment.close()
        segment.unlink()


@needs_c
def test_failed_simulations_kept_in_reference_cycles_do_not_corrupt_memory(tmp_path: Path, monkeypatch) -> None:
    """A failure's traceback keeps the task (and its C core) in a cycle; the collector must not free
    the shared memory under the core's views (this crashed the interpreter later, at random)."""
    monkeypatch.delenv(hotpath.PURE_PYTHON_ENV, raising=False)
    kept = []
    for i in range(25):
        app = App(f"hotpath_cycle_{os.getpid()}_{i}")
        app.record(app.add_task("bad", RaiseAt(cycle=7), period_ns=P).y)
        with pytest.raises(rtloop.TaskFailed) as failure:
            rtloop.simulate(app, 1.0, tmp_path / str(i))
        kept.append(failure.value)
    kept.clear()
    gc.collect()
    junk = [bytearray(4096) for _ in range(20_000)]  # reuse what was freed; a dangling view would show
    assert sum(len(b) for b in junk) == 4096 * 20_000


@pytest.mark.rt
@pytest.mark.parametrize("lock_blas_buffer", [False, True])
def test_a_matrix_product_in_the_loop_does_not_map_a_new_blas_buffer(tmp_path: Path, lock_blas_buffer: bool) -> None:
    # Before: OpenBLAS mapped a second 32 MB buffer on the first product, and mlockall faulted
    # it all in inside the loop (8,192 faults). Now the one buffer exists before the loop.
    # 100 cycles wherever it runs: at 2 ms unstretched, the emulated guest skipped half of them
    app = App(f"blas_{os.getpid()}_{int(lock_blas_buffer)}")
    product = app.add_task("product", MatrixProduct(), period_ns=scaled_ns(2_000_000), cpu=other_cpu(),
                           lock_blas_buffer=lock_blas_buffer)
    app.record(product.y)
    summary = rtloop.run(app, scaled_s(0.2), tmp_path)
    assert summary.rt_capable
    header, *rows = rows_of(tmp_path / "signals.csv")
    faults = [float(row[header.index("product.y[0]")]) for row in rows[1:]]  # row 0: initial outputs
    assert len(faults) > 50
    # Unlocked, the product faults in the few pages it packs into, once; locked, none at all.
    assert max(faults) <= (0 if lock_blas_buffer else 16), faults[:5]


def test_a_task_process_imports_neither_the_supervisor_nor_the_recorder(rtloop_env) -> None:
    # Every task process imports rtloop.runtime.task (it unpickles its entry point); whatever
    # that drags in is mapped, and locked by mlockall, in each of them.
    code = ("import sys, rtloop.runtime.task\n"
            "heavy = ['rtloop.runtime.supervisor', 'rtloop.record.recorder', 'rtloop.record.summary', 'hashlib']\n"
            "print([name for name in heavy if name in sys.modules])\n"
            "import rtloop\nprint(rtloop.run.__module__, rtloop.RunSummary.__name__)")
    result = subprocess.run([sys.executable, "-c", code], env=rtloop_env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == ["[]", "rtloop.runtime.supervisor RunSummary"]
