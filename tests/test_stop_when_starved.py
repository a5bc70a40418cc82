"""Ctrl-C ends a run whose tasks starve the supervisor, quickly, and says what was not recorded.

Two 50 kHz tasks, everything recorded, one on each processor at a real-time priority above the
supervisor's: the tasks leave the supervisor crumbs, it falls far behind the recording, and
their queues fill. Before the fix a SIGINT waited for the supervisor's next turn (the tasks went
on meanwhile) and then for the whole backlog to be written: 7-22 s. Now the signal handler
stops the tasks itself and the drain after the stop has a time budget; what it leaves is
counted as lost, and signals.csv marks the gap.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from conftest import skip_in_rtkernel_guest
from rtloop.ipc.ports import connect_app

STOP_BOUND_S = 3.0
"""Generous for a loaded 2-core machine: the stop is designed to take about 1 s (the
drain after the stop, 0.3 s), and took 2.7-22 s before."""


def _app_file(tmp_path: Path, name: str, cpus: list[int]) -> Path:
    path = tmp_path / f"{name}.toml"
    tasks = "".join(
        f'[tasks.{task}]\nrunnable = "rt_test_runnables:Counter"\nperiod_ns = 20_000\n'
        f"priority = {priority}\ncpu = {cpu}\n"
        for task, priority, cpu in (("a", 70, cpus[0]), ("b", 60, cpus[1])))
    path.write_text(f'name = "{name}"\n{tasks}[record]\nsignals = ["a.y", "b.y"]\n')
    return path


def _wait_running(name: str, timeout_s: float = 60) -> None:
    app = connect_app(name, timeout_s=timeout_s)
    deadline = time.monotonic() + timeout_s
    while not all(app.task_pids().values()):
        assert time.monotonic() < deadline, "the tasks did not start"
        time.sleep(0.05)


def _starve_and_interrupt(tmp_path: Path, name: str, cpus: list[int], env: dict[str, str]) -> tuple[float, int, str]:
    """Start the starving app, let its queues fill, send SIGINT: (seconds to the end, exit code, stderr)."""
    out = tmp_path / "out"
    process = subprocess.Popen(
        [sys.executable, "-m", "rtloop.cli", "run", str(_app_file(tmp_path, name, cpus[-2:])), "--out", str(out)],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    said: list[str] = []
    behind = threading.Event()

    def read_stderr() -> None:
        assert process.stderr is not None
        for line in process.stderr:
            said.append(line)
            if "falls behind the recording" in line:
                behind.set()

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    try:
        _wait_running(name)
        # The queues fill and the supervisor says it falls behind: about 3 s on a quiet machine, longer
        # when the machine is busier still (3 s fixed once left the console without the notice).
        time.sleep(3)
        behind.wait(60)
        sent_at = time.monotonic()
        process.send_signal(signal.SIGINT)
        process.wait(timeout=60)
        stop_s = time.monotonic() - sent_at
        reader.join(60)
        return stop_s, process.returncode, "".join(said)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        reader.join(60)
        if process.stderr is not None:
            process.stderr.close()


@pytest.mark.rt
@pytest.mark.slow
@skip_in_rtkernel_guest("the scenario needs tasks at 50 kHz that fill their 65,536-record rings within seconds; "
                        "emulated tasks run ~20x slower, never fill them, and nothing is lost to count")
@pytest.mark.alone
def test_ctrl_c_ends_a_run_that_starves_the_supervisor_and_reports_what_was_lost(tmp_path: Path, rtloop_env):
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        pytest.skip("needs two processors: one busy task on each starves the supervisor")
    name = f"starved_stop_{os.getpid()}"
    # A second try when the first stop took too long: real-time work of other runs on this shared
    # machine can hold the supervisor off for seconds now and then. Two slow stops in a row fail
    # (the old behaviour, the whole backlog written first, was slow in nearly every run).
    for attempt in range(2):
        attempt_path = tmp_path / f"attempt{attempt}"
        attempt_path.mkdir()
        stop_s, returncode, stderr = _starve_and_interrupt(attempt_path, name, cpus, rtloop_env)
        if returncode != 0 or stop_s < STOP_BOUND_S:
            break
    out = attempt_path / "out"
    assert returncode == 0, stderr
    assert stop_s < STOP_BOUND_S, f"SIGINT took {stop_s:.1f} s to end the run (twice)"

    summary = json.loads((out / "summary.json").read_text())
    assert summary["stopped_by"] == "signal"
    lost = summary["recording"]["lost"]
    # what the queues dropped during the run, and what was left unwritten at the stop, are counted
    assert set(lost) >= {"timing_records", "signal_rows", "timing_records_at_stop", "signal_rows_at_stop"}
    assert sum(lost["signal_rows"].values()) + sum(lost["signal_rows_at_stop"].values()) > 0
    assert sum(lost["timing_records"].values()) + sum(lost["timing_records_at_stop"].values()) > 0
    assert any("signal rows lost" in note or "signal rows not written" in note for note in summary["notes"])
    assert "falls behind the recording" in stderr

    with open(out / "signals.csv", newline="") as file:
        rows = list(csv.reader(file))
    header, body = rows[0], rows[1:]
    assert header == ["t_s", "a.y[0]", "a.y[1]", "b.y[0]", "b.y[1]"]
    gaps = [row for row in body if "" in row[1:]]
    assert gaps, "lost rows must be marked as empty cells in signals.csv, never filled with the last value"
    assert not list(Path("/dev/shm").glob(f"rtloop-{name}-*")), "shared memory left behind"


def test_what_the_drain_after_the_stop_leaves_is_counted_and_marked_as_a_gap(tmp_path: Path) -> None:
    """No processes: records pushed into the shared-memory queues as a task would, then the
    drain after the stop with no time at all: one batch is written, the rest counted."""
    import numpy as np

    from rt_test_runnables import Counter
    from rtloop import App
    from rtloop.runtime.session import DRAIN_BATCH_RECORDS, RunSession

    app = App(f"stop_budget_{os.getpid()}")
    task = app.add_task("a", Counter(), period_ns=1_000_000, policy="other")
    app.record(task.y)
    pushed = 3 * DRAIN_BATCH_RECORDS
    with RunSession(app, tmp_path / "out", mode="run", duration_s=None, keep_s=None, trim=0,
                    registry=False) as session:
        handles = session.layout.tasks["a"]
        assert handles.record is not None
        for cycle in range(pushed):
            release_ns = cycle * 1_000_000
            assert handles.timing.push4(cycle, release_ns, release_ns + 10, release_ns + 20)
            assert handles.record.push(cycle, np.array([cycle + 1.0, cycle / 1000]))
        session.drain_after_stop(0.0)
        assert session.losses.timing_at_stop == {"a": pushed - DRAIN_BATCH_RECORDS}
        assert session.losses.signal_rows_at_stop == {"a": pushed - DRAIN_BATCH_RECORDS}
        assert session.losses.to_json()["lost"]["signal_rows_at_stop"] == {"a": pushed - DRAIN_BATCH_RECORDS}
        assert any("not written" in note for note in session.losses.notes())
    with open(tmp_path / "out" / "signals.csv", newline="") as file:
        rows = list(csv.reader(file))[1:]
    # the rows of the batch written (no initial outputs were pushed), then one row that marks the gap
    assert len(rows) == DRAIN_BATCH_RECORDS + 1
    assert rows[-2][1:] == [repr(float(DRAIN_BATCH_RECORDS)), repr((DRAIN_BATCH_RECORDS - 1) / 1000)]
    assert rows[-1] == [repr((DRAIN_BATCH_RECORDS + 1) / 1000), "", ""]
    with open(tmp_path / "out" / "timing.csv", newline="") as file:
        assert len(list(csv.reader(file))) == 1 + DRAIN_BATCH_RECORDS
