"""``rtloop.load``: a run, a simulation, a failed run and a killed ``--keep`` run as numpy arrays."""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import rtloop
from conftest import wait_for_app, wait_for_cycles
from rt_test_runnables import Counter, Gain, RaiseAt
from rtloop.record.load import LoadError

MS = 1_000_000


def csv_columns(path: Path) -> dict[str, list[str]]:
    """signals.csv read the plain way, as text, for comparison."""
    with open(path, newline="") as file:
        rows = list(csv.reader(file))
    return {name: [row[i] for row in rows[1:]] for i, name in enumerate(rows[0])}


def as_floats(cells: list[str]) -> np.ndarray:
    return np.array([float(c) if c else math.nan for c in cells])


def counter_app(name: str) -> rtloop.App:
    app = rtloop.App(name)
    counter = app.add_task("counter", Counter(), period_ns=MS, policy="other")
    gain = app.add_task("gain", Gain(1), period_ns=2 * MS, policy="other")
    app.port("offset", to=gain.u[0])
    app.record(counter.y, gain.y)
    return app


# --- a simulation -----------------------------------------------------------------------------
def test_a_simulation_loads_as_the_files_say(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    rtloop.simulate(counter_app("load_sim"), 0.5, out, port_writes={("gain", 40): [("offset", [2.5])],
                                                                    ("gain", 100): [("offset", [-1.0])]})
    run = rtloop.load(out)
    assert isinstance(run, rtloop.RunData)
    assert run.mode == "simulate" and run.failure is None and run.problems == []
    text = csv_columns(out / "signals.csv")
    assert list(run.signals) == list(text)[1:]
    np.testing.assert_array_equal(run.signals.t_s, as_floats(text["t_s"]))
    for name in run.signals:
        np.testing.assert_array_equal(run.signals[name], as_floats(text[name]))
        assert run.signals[name].dtype == np.float64
    assert run.signals.rows == 501 and run.signals.gaps.shape == (0, 2)
    # timing: int64 arrays per task, every cycle
    counter = run.timing["counter"]
    assert counter.release_ns.dtype == np.int64 and len(counter) == 500
    np.testing.assert_array_equal(counter.cycle, np.arange(500))
    assert np.all(np.diff(counter.release_ns) == MS) and len(run.timing["gain"]) == 250
    # the live port writes, with the cycle and time at which the task took them
    offset = run.inputs["offset"]
    assert offset.task == "gain"
    np.testing.assert_array_equal(offset.cycle, [40, 100])
    np.testing.assert_array_equal(offset.t_s, [0.08, 0.2])
    np.testing.assert_array_equal(offset.values, [[2.5], [-1.0]])
    # the gain's output follows the offset from the release that took it, plus one period (LET)
    gain = run.signals["gain.y[0]"]
    assert gain[np.searchsorted(run.signals.t_s, 0.082)] == 2.5


def test_a_port_without_live_values_says_why_it_has_none(tmp_path: Path) -> None:
    gain = rtloop.App("load_noinput")
    task = gain.add_task("gain", Gain(2), period_ns=MS, policy="other")
    gain.port("setpoint", to=task.u[0:1], feed=str(_profile(tmp_path)))
    gain.port("offset", to=task.u[1:2])
    gain.port("out", source=task.y)
    rtloop.simulate(gain, 0.05, tmp_path / "sim")
    run = rtloop.load(tmp_path / "sim")
    assert dict(run.inputs) == {}
    for name, said in (("setpoint", "was fed from .* not written live: its values are in run.signals"),
                       ("offset", "took no live value in this run"),
                       ("out", "is an output port"),
                       ("nope", r"no input port 'nope' in this run \(its input ports: \['offset', 'setpoint'\]\)")):
        with pytest.raises(KeyError, match=said):
            run.inputs[name]


def _profile(tmp_path: Path) -> Path:
    path = tmp_path / "profile.csv"
    path.write_text("t_s,v\n0.0,1.0\n0.02,2.0\n")
    return path


def test_to_pandas(tmp_path: Path) -> None:
    pandas = pytest.importorskip("pandas", reason="pandas is an optional extra: pip install 'rtloop[pandas]'")
    out = tmp_path / "sim"
    rtloop.simulate(counter_app("load_pandas"), 0.1, out)
    run = rtloop.load(out)
    frame = run.signals.to_pandas()
    assert isinstance(frame, pandas.DataFrame)
    assert list(frame.columns) == list(run.signals) and frame.index.name == "t_s"
    np.testing.assert_array_equal(frame["counter.y[0]"].to_numpy(), run.signals["counter.y[0]"])


# --- a failed run -----------------------------------------------------------------------------
def test_a_failed_simulation_loads_up_to_the_failure(tmp_path: Path) -> None:
    app = rtloop.App("load_failed")
    task = app.add_task("boom", RaiseAt(70), period_ns=MS, policy="other")
    app.record(task.y)
    with pytest.raises(rtloop.TaskFailed):
        rtloop.simulate(app, 1.0, tmp_path / "failed")
    run = rtloop.load(tmp_path / "failed")
    assert run.failure is not None and run.failure["task"] == "boom" and run.failure["cycle"] == 70
    assert "ZeroDivisionError" in run.failure["reason"]
    assert len(run.timing["boom"]) == 70  # cycles 0..69 ended; cycle 70 raised
    assert run.signals["boom.y[0]"][-1] == 69


# --- a real run with a live port write ---------------------------------------------------------
APP_FILE = """
name = "{name}"
[tasks.counter]
runnable = "rt_test_runnables:Counter"
period_ns = 1_000_000
policy = "other"
[tasks.gain]
runnable = "rt_test_runnables:Gain"
args = {{ n = 1 }}
period_ns = 2_000_000
policy = "other"
[ports.offset]
to = "gain.u[0]"
[record]
signals = ["counter.y", "gain.y"]
"""


def test_a_real_run_loads_with_its_live_inputs(tmp_path: Path, rtloop_env) -> None:
    name = f"load_run_{os.getpid() % 100000}"
    app_file = tmp_path / f"{name}.toml"
    app_file.write_text(APP_FILE.format(name=name))
    out = tmp_path / "run"
    cli = [sys.executable, "-m", "rtloop.cli"]
    # Until Ctrl-C, once the write has been taken and 200 cycles of gain have run after it (the
    # duration is only a bound): however slow the machine, the run has rows after the write.
    process = subprocess.Popen([*cli, "run", str(app_file), "--duration", "200", "--out", str(out), "-q"],
                               env=rtloop_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while True:  # a loaded machine can take seconds to start the app
            write = subprocess.run([*cli, "port", "write", name, "offset", "4.25"], env=rtloop_env,
                                   capture_output=True, text=True)
            if write.returncode == 0 or time.monotonic() > deadline or process.poll() is not None:
                break
            time.sleep(0.2)
        assert write.returncode == 0, write.stderr
        app = wait_for_app(name, process)
        written_at = wait_for_cycles(app, "gain", 1, process)
        wait_for_cycles(app, "gain", written_at + 200, process)
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
        _, err = process.communicate(timeout=60)
    assert process.returncode == 0, err
    run = rtloop.load(out)
    summary = json.loads((out / "summary.json").read_text())
    assert run.summary == summary and run.mode == "run"
    for task in ("counter", "gain"):
        assert len(run.timing[task]) == summary["tasks"][task]["cycles"]
        timing = run.timing[task]
        assert np.all(timing.start_ns >= timing.release_ns) and np.all(timing.end_ns >= timing.start_ns)
    offset = run.inputs["offset"]
    assert offset.values.tolist() == [[4.25]] and offset.task == "gain"
    # a write before T0 is taken at cycle 0, a later one inside the run (each try above is a Python start:
    # seconds on a loaded machine, so not within the run's first seconds)
    assert 0 <= offset.t_s[0] < run.signals.t_s[-1]
    after = run.signals.t_s > offset.t_s[0] + 0.002 + 1e-9
    assert np.count_nonzero(after) >= 100, "the run has too few rows after the write to show it"
    assert np.all(run.signals["gain.y[0]"][after] == 4.25)


# --- a killed --keep run ----------------------------------------------------------------------
def test_a_run_killed_during_keep_loads_from_its_segments(tmp_path: Path, rtloop_env) -> None:
    name = f"load_kill_{os.getpid() % 100000}"
    app_file = tmp_path / f"{name}.toml"
    app_file.write_text(APP_FILE.format(name=name))
    out = tmp_path / "killed"
    process = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--keep", "6",
                                "--out", str(out), "-q"], env=rtloop_env, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(list((out / "segments").glob("*-timing.csv"))) < 3:
            time.sleep(0.2)
        assert len(list((out / "segments").glob("*-timing.csv"))) >= 3, "no segments written"
        time.sleep(0.3)
    finally:
        os.killpg(process.pid, signal.SIGKILL)  # the supervisor and its task processes: nothing is joined
        process.wait(timeout=30)
    run = rtloop.load(out)
    assert any("segment" in p for p in run.problems)
    assert any("did not end normally" in p for p in run.problems)
    counter = run.timing["counter"]
    assert len(counter) > 500 and np.all(np.diff(counter.cycle) > 0)  # a loaded machine skips releases
    t_s = run.signals.t_s
    assert t_s.size > 500 and np.all(np.diff(t_s) > 0)
    assert not np.any(np.isnan(run.signals["counter.y[1]"][1:]))
    # whatever was written last, cut in the middle, is left out and said so, never misread
    for problem in run.problems:
        assert "line" not in problem or "incomplete" in problem


# --- bad files, gaps, large runs --------------------------------------------------------------
def write_synthetic(out: Path, signals: str, timing: str = "", tasks: tuple[str, ...] = ("a",)) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    entry = {"period_ns": MS, "cycles": 0}
    (out / "summary.json").write_text(json.dumps({"app": "x", "mode": "run", "tasks": dict.fromkeys(tasks, entry),
                                                  "recording": {"keep_s": 1}}))
    (out / "signals.csv").write_text(signals)
    (out / "timing.csv").write_text("task,cycle,release_ns,start_ns,end_ns\n" + timing)
    return out


def test_gaps_stay_gaps(tmp_path: Path) -> None:
    out = write_synthetic(tmp_path / "gaps", "t_s,a.y[0],a.y[1]\n0.0,1.0,\n0.001,,2.0\n0.002,nan,3.0\n"
                                             "0.005,4.0,5.0\n0.006,inf,-inf\n")
    run = rtloop.load(out)
    np.testing.assert_array_equal(run.signals["a.y[0]"], [1.0, np.nan, np.nan, 4.0, np.inf])
    np.testing.assert_array_equal(run.signals["a.y[1]"], [np.nan, 2.0, 3.0, 5.0, -np.inf])
    np.testing.assert_array_equal(run.signals.gaps, [[0.002, 0.005]])  # rows 3 and 4 ms are missing


def test_task_names_that_are_prefixes_of_each_other(tmp_path: Path) -> None:
    rows = "".join(f"{t},{k},{k * MS},{k * MS + 5},{k * MS + 9}\n" for k in range(5) for t in ("ab", "a", "b"))
    out = write_synthetic(tmp_path / "names", "t_s,a.y[0]\n0.0,1.0\n", rows, tasks=("a", "ab", "b"))
    run = rtloop.load(out)
    for task in ("a", "ab", "b"):
        np.testing.assert_array_equal(run.timing[task].cycle, np.arange(5))
        np.testing.assert_array_equal(run.timing[task].end_ns, np.arange(5) * MS + 9)


def test_a_cut_last_line_and_a_bad_line_are_left_out_and_reported(tmp_path: Path) -> None:
    out = write_synthetic(tmp_path / "cut", "t_s,a.y[0]\n0.0,1.0\n0.001,zz\n0.002,3.0\n0.003,4.0\n0.00",
                          "a,0,0,1,2\na,1,1000000,1000001,1000002\na,2,2000")
    run = rtloop.load(out)
    np.testing.assert_array_equal(run.signals.t_s, [0.0, 0.002, 0.003])
    assert len(run.timing["a"]) == 2
    assert any("signals.csv line 3" in p and "left out" in p for p in run.problems)
    assert any("signals.csv line 6: the last line is incomplete" in p for p in run.problems)
    assert any("timing.csv line 4: the last line is incomplete" in p for p in run.problems)


def test_a_large_run_is_memory_mapped_and_equal(tmp_path: Path) -> None:
    rows = "".join(f"{k / 1000!r},{math.sin(k)!r},{k}\n" for k in range(20_000))
    timing = "".join(f"a,{k},{k * MS},{k * MS + 7},{k * MS + 11}\n" for k in range(20_000))
    out = write_synthetic(tmp_path / "big", "t_s,a.y[0],a.y[1]\n" + rows, timing)
    in_memory = rtloop.load(out)
    mapped = rtloop.load(out, memory_limit_bytes=0)
    assert isinstance(mapped.signals.table.base, np.memmap) or isinstance(mapped.signals.table, np.memmap)
    np.testing.assert_array_equal(mapped.signals.table, in_memory.signals.table)
    np.testing.assert_array_equal(mapped.timing["a"].end_ns, in_memory.timing["a"].end_ns)
    assert sorted(os.listdir(out)) == ["signals.csv", "summary.json", "timing.csv"]  # nothing left behind


def test_not_a_run_directory(tmp_path: Path) -> None:
    with pytest.raises(LoadError, match="no such run directory"):
        rtloop.load(tmp_path / "nope")
    with pytest.raises(LoadError, match=r"no summary\.json"):
        rtloop.load(tmp_path)
    (tmp_path / "summary.json").write_text("[1, 2]")
    with pytest.raises(LoadError, match="not an rtloop summary"):
        rtloop.load(tmp_path)


def test_public_names_resolve() -> None:
    for name in rtloop.__all__:
        assert getattr(rtloop, name) is not None, name
    assert rtloop.load is rtloop.record.load.load
