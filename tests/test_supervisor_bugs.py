"""Supervisor-side bugs of a careful review: each test here failed before its fix."""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import rtloop
from rt_test_runnables import Counter
from rtloop import App
from rtloop.app.builder import SignalRef
from rtloop.ipc.segments import SHM_DIR
from rtloop.linux import rt
from rtloop.record.csvfiles import SignalsCsv

P = 1_000_000
CLI = [sys.executable, "-m", "rtloop.cli"]


def segments_of(app_name: str) -> list[str]:
    return sorted(p.name for p in SHM_DIR.glob(f"rtloop-{app_name}-*"))


def counter_app(name: str, period_ns: int = P) -> App:
    app = App(name)
    task = app.add_task("count", Counter(), period_ns=period_ns, policy="other")
    app.record(task.y)
    return app


def read_rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as file:
        return list(csv.reader(file))


# --- profiles respect a port's range ------------------------------------------------------------


def test_a_feed_outside_the_ports_range_is_refused_naming_file_row_and_column(tmp_path: Path, rtloop_env) -> None:
    profile = tmp_path / "setpoint.csv"
    profile.write_text("t_s,speed\n0,0.5\n0.01,7.5\n")
    app_file = tmp_path / "ranged.toml"
    app_file.write_text('name = "ranged"\n[tasks.c]\nrunnable = "rt_test_runnables:Gain"\nperiod_ns = 1_000_000\n'
                        '[ports.speed]\nto = "c.u[0]"\nrange = [-1.0, 1.0]\n')
    result = subprocess.run([*CLI, "simulate", str(app_file), "--duration", "0.02", "--out", str(tmp_path / "o"),
                             "--feed", f"speed={profile}"], env=rtloop_env, capture_output=True, text=True)
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert f"{profile}:3" in result.stderr and "'speed'" in result.stderr and "7.5" in result.stderr
    assert not (tmp_path / "o").exists()  # refused before the folder was touched


# --- nothing leaks when a simulation fails to start ----------------------------------------------


def test_a_bad_trim_is_one_line_exit_2_and_leaks_no_shared_memory(tmp_path: Path, rtloop_env) -> None:
    app_file = tmp_path / "trimmed.toml"
    name = f"trim_{os.getpid()}"
    app_file.write_text(f'name = "{name}"\n[tasks.c]\nrunnable = "rt_test_runnables:Counter"\nperiod_ns = 1_000_000\n')
    result = subprocess.run([*CLI, "simulate", str(app_file), "--duration", "0.02", "--out", str(tmp_path / "o"),
                             "--trim", "-1"], env=rtloop_env, capture_output=True, text=True)
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "--trim" in result.stderr and "internal error" not in result.stderr
    assert segments_of(name) == []


def test_a_failure_between_the_layout_and_the_run_leaks_no_shared_memory(tmp_path: Path, monkeypatch) -> None:
    from rtloop.record import recorder

    def broken(*_args, **_kwargs) -> None:
        raise RuntimeError("the recorder could not start")

    monkeypatch.setattr(recorder.Recorder, "__init__", broken)
    name = f"leak_{os.getpid()}"
    with pytest.raises(RuntimeError, match="could not start"):
        rtloop.simulate(counter_app(name), 0.02, tmp_path / "o")
    assert segments_of(name) == []
    assert not (tmp_path / "o" / ".summary-reserve").exists()


# --- a second Ctrl-C during the final flush ------------------------------------------------------


@pytest.mark.skipif(importlib.util.find_spec("mcap") is None, reason="metadata.yaml needs the mcap package")
def test_a_second_ctrl_c_during_the_final_flush_keeps_summary_and_metadata(tmp_path: Path, monkeypatch) -> None:
    from rtloop.record import recorder

    close = recorder.Recorder.close

    def interrupted_close(self) -> None:
        os.kill(os.getpid(), signal.SIGINT)  # delivered now, in the middle of the flush
        time.sleep(0.05)
        close(self)

    monkeypatch.setattr(recorder.Recorder, "close", interrupted_close)
    out = tmp_path / "o"
    # Ctrl-C's usual handler, whatever pytest inherited: a process started as a background job (`cmd &`
    # in a script, nohup) begins with SIGINT ignored, Python then installs no handler for it, and a
    # Ctrl-C held back during the flush is rightly dropped afterwards.
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):  # honoured, once everything is written
            rtloop.simulate(counter_app(f"ctrlc_{os.getpid()}"), 0.05, out)
    finally:
        signal.signal(signal.SIGINT, inherited)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["running"] is False and summary["tasks"]["count"]["cycles"] == 50
    assert (out / "metadata.yaml").exists()


# --- the caller of rtloop.run keeps its children and is not left a subreaper -----------------------


@pytest.mark.rt
def test_run_from_a_library_spares_the_callers_children_and_its_subreaper_state(tmp_path: Path) -> None:
    assert not rt.is_subreaper()
    started: list[subprocess.Popen] = []

    def start_a_child_meanwhile() -> None:
        time.sleep(0.3)
        started.append(subprocess.Popen(["sleep", "30"]))

    thread = threading.Thread(target=start_a_child_meanwhile)
    thread.start()
    try:
        rtloop.run(counter_app(f"lib_{os.getpid()}"), 1.0, tmp_path / "o")
        thread.join()
        assert started and started[0].poll() is None, "the caller's own child was killed by the run's cleanup"
        assert not rt.is_subreaper(), "the caller stayed a subreaper after the run"
    finally:
        thread.join()
        for child in started:
            child.kill()
            child.wait()


# --- a task's traceback is not lost when it exits between two looks --------------------------------


class _Pipe:
    """A pipe whose message arrives only after the process was seen to have exited."""

    def __init__(self, process) -> None:
        self.process, self.messages = process, []

    def poll(self) -> bool:
        if not self.messages and self.process.exitcode is not None and not self.process.delivered:
            self.process.delivered = True
            self.messages.append({"kind": "failed", "cycle": 3, "phase": "step", "reason": "ValueError: boom",
                                  "traceback": "Traceback ... ValueError: boom"})
        return bool(self.messages)

    def recv(self):
        return self.messages.pop(0)


class _ExitingProcess:
    """Alive at the first read of the pipe, exited (code 1) by the time its exit code is asked."""

    def __init__(self) -> None:
        self.looks, self.delivered = 0, False

    @property
    def exitcode(self):
        self.looks += 1
        return None if self.looks == 1 else 1


def test_a_task_that_exits_between_the_pipe_read_and_the_exit_check_keeps_its_traceback(tmp_path: Path) -> None:
    from rtloop.runtime.layout import AppLayout
    from rtloop.runtime.supervisor import Supervisor
    from rtloop.runtime.task_watch import TaskProcess as _TaskRun

    app = counter_app(f"race_{os.getpid()}")
    supervisor = Supervisor(app, 0.1, tmp_path / "o", trim=0)
    layout = AppLayout.create(app)
    try:
        process = _ExitingProcess()
        supervisor.runs = {"count": _TaskRun("count", process, None)}
        supervisor.runs["count"].pipe = _Pipe(process)
        assert process.exitcode is None  # the first look: the read above found nothing, the process ran
        supervisor._poll(layout)
    finally:
        layout.close()
    assert supervisor.failure is not None
    assert supervisor.failure.traceback_text == "Traceback ... ValueError: boom"
    assert supervisor.failure.cycle == 3


# --- lost rows are gaps in signals.csv, never a plateau ------------------------------------------


def test_signals_csv_marks_lost_rows_as_empty_cells_not_the_last_value(tmp_path: Path) -> None:
    path = tmp_path / "signals.csv"
    writer = SignalsCsv(path, [SignalRef("a", "y", 0, 1)], {"a": P}, {"a": 1})
    writer.add("a", np.array([-1, 0, 1]), np.array([[0.0], [1.0], [2.0]]))
    writer.flush()
    # ticks 2..4 were dropped by the full record queue (3 rows), then 5 and 6 came
    writer.add("a", np.array([5, 6]), np.array([[6.0], [7.0]]), lost_so_far=3)
    writer.flush(final=True)
    writer.close()
    rows = read_rows(path)
    assert rows[0] == ["t_s", "a.y[0]"]
    by_time = {row[0]: row[1] for row in rows[1:]}
    assert by_time["0.002"] == "2.0"
    assert by_time["0.003"] == "", "the first lost value is an empty cell, not 2.0 held on"
    assert by_time["0.006"] == "6.0" and by_time["0.007"] == "7.0"


def test_a_skipped_release_without_losses_holds_the_last_value(tmp_path: Path) -> None:
    path = tmp_path / "signals.csv"
    writer = SignalsCsv(path, [SignalRef("a", "y", 0, 1), SignalRef("b", "y", 0, 1)], {"a": P, "b": P},
                        {"a": 1, "b": 1})
    writer.add("a", np.array([-1, 0, 3]), np.array([[0.0], [1.0], [4.0]]))  # releases 1 and 2 skipped
    writer.add("b", np.array([-1, 0, 1, 2, 3]), np.array([[0.0], [1.0], [2.0], [3.0], [4.0]]))
    writer.flush(final=True)
    writer.close()
    by_time = {row[0]: row[1] for row in read_rows(path)[1:]}
    assert by_time["0.002"] == "1.0" and by_time["0.003"] == "1.0"  # under LET the last output holds


# --- full precision ----------------------------------------------------------------------------


def test_signals_csv_values_read_back_as_the_same_floats(tmp_path: Path) -> None:
    path = tmp_path / "signals.csv"
    rng = np.random.default_rng(7)
    values = np.concatenate((rng.standard_normal((500, 3)) * 10.0 ** rng.integers(-300, 300, (500, 3)),
                             [[np.nan, np.inf, -np.inf], [5e-324, 1.7976931348623157e308, -0.0],
                              [0.1, 1 / 3, 2 / 3]]))
    ticks = np.arange(-1, len(values) - 1)
    writer = SignalsCsv(path, [SignalRef("a", "y", 0, 3)], {"a": 3_000_017}, {"a": 3})
    writer.add("a", ticks, values)
    writer.flush(final=True)
    writer.close()
    rows = read_rows(path)[1:]
    assert len(rows) == len(values)
    read = np.array([[float(cell) for cell in row[1:]] for row in rows])
    assert np.array_equal(read, values, equal_nan=True)
    assert np.array_equal(np.signbit(read), np.signbit(values))
    assert rows[-1][1:] == ["0.1", "0.3333333333333333", "0.6666666666666666"]  # repr: the shortest exact text
    assert [round(float(row[0]) * 1e9) for row in rows] == [(k + 1) * 3_000_017 for k in ticks.tolist()]
