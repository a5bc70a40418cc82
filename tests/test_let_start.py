"""Logical execution time from the very first release: the initial outputs are there before any task starts.

A task's initial outputs (what ``prerun`` left in ``y``) hold from T0. They are published while
the task prepares, before it says it is ready, so before the supervisor even picks T0: a reader
released at T0 finds them however late its writer sees T0 (a loaded machine), exactly as in
``rtloop simulate``, and a run and its replay agree from the first row.
"""

from __future__ import annotations

import csv
import multiprocessing
import os
from pathlib import Path

import numpy as np
import pytest

import rtloop
from conftest import other_cpu
from rtloop import App
from rtloop.ipc.channels import NO_STAMP, LetChannel
from rtloop.ipc.ring import Int64Ring
from rtloop.ipc.schema import INITIAL_STAMP
from rtloop.ipc.segments import Segment, new_run_token
from rtloop.ipc.wiring import READ_LOG_WIDTH, InputLink, TaskWiring, TaskWiringPlan

P = 1_000_000
T0 = 7_000_000_000
LATE_S = 0.3
"""How long the late writer dawdles after it has seen T0 (the start margin is 0.1 s)."""
INITIAL = [0.5, -0.25]


class LateStartingPlant(rtloop.Runnable):
    """A plant with non-zero initial outputs that starts late, as a task held off by other load
    does: its prerun makes its own process go on 0.3 s after it has seen T0."""

    n_inputs = n_outputs = 2

    def __init__(self) -> None:
        self.x = list(INITIAL)
        self.initial_outputs = list(INITIAL)

    def prerun(self) -> None:
        if multiprocessing.parent_process() is not None:  # in a task process only, never in the tests' own
            import time

            import rtloop.runtime.task as task_process

            seen = task_process._wait_for_epoch

            def seen_late(control):
                epoch = seen(control)
                time.sleep(LATE_S)
                return epoch

            task_process._wait_for_epoch = seen_late

    def step(self, u, y) -> None:
        for i in range(2):
            self.x[i] += 0.003 * (u[i] - self.x[i])
            y[i] = self.x[i]


class Follower(rtloop.Runnable):
    """y = 2·u: shows what it read at every cycle."""

    n_inputs = n_outputs = 2

    def step(self, u, y) -> None:
        y[:] = 2.0 * u


def _app(name: str) -> App:
    app = App(name)
    follower = app.add_task("follower", Follower(), period_ns=P, cpu=other_cpu())
    plant = app.add_task("plant", LateStartingPlant(), period_ns=P, cpu=other_cpu(), priority=81)
    app.connect(plant.y, follower.u)
    app.connect(follower.y, plant.u)
    app.record(plant.y, follower.y, follower.u)
    return app


def _rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as file:
        return list(csv.reader(file))


def test_initial_outputs_are_published_before_t0_and_read_as_stamped_t0(monkeypatch) -> None:
    """At the wiring: published at prerun (T0 not yet known), read at T0 as the LET sample (no stale
    read), and at T0 + P as a stale read of the sample stamped 0 (since T0), never as "no sample"."""
    monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
    token, pid = new_run_token(), os.getpid()
    made = [Segment.create("letstart", pid, token, "w", LetChannel.size_bytes(2, 2)),
            Segment.create("letstart", pid, token, "reads", Int64Ring.size_bytes(8, READ_LOG_WIDTH))]
    try:
        LetChannel.initialise(made[0], 2, 2)
        Int64Ring.initialise(made[1], 8, READ_LOG_WIDTH)
        writer = TaskWiring(TaskWiringPlan(output_channel=made[0].name, segments=(made[0].name,)),
                            np.zeros(0), np.zeros(2), None)
        writer.publish_initial(np.array(INITIAL))
        assert LetChannel(made[0]).published == 1, "published before T0 is known"
        reader = TaskWiring(TaskWiringPlan(inputs=(InputLink(made[0].name, slice(0, 2), slice(0, 2), P, "w"),),
                                           read_log=made[1].name, segments=(made[0].name, made[1].name)),
                            np.zeros(2), np.zeros(0), None)
        reader.t0_ns = T0
        reader.read_inputs(T0, reader.u)
        assert reader.u.tolist() == INITIAL and reader.stale_reads == 0
        reader.read_inputs(T0 + P, reader.u)  # the writer has not published cycle 0 yet
        assert Int64Ring(made[1]).drain().tolist() == [[P, 0, INITIAL_STAMP, P]]
        assert INITIAL_STAMP != NO_STAMP
    finally:
        for segment in made:
            segment.unlink()


@pytest.mark.rt
@pytest.mark.timeout(240)
def test_a_writer_that_sees_t0_late_still_gives_its_initial_outputs_at_the_first_release(
        tmp_path: Path, hot_path: str) -> None:
    from rtloop.runtime.replay import replay

    name = f"let_start_{hot_path}_{os.getpid()}"
    summary = rtloop.run(_app(name), 1.0, tmp_path / "run")
    timing = [row for row in _rows(tmp_path / "run" / "timing.csv")[1:] if row[0] == "plant"]
    late_ns = int(timing[0][3]) - int(timing[0][2])
    if late_ns < 2 * P:
        pytest.skip(f"the plant saw T0 only {late_ns} ns late: nothing to prove")
    reads = _rows(tmp_path / "run" / "reads.csv")
    assert reads[0] == ["task", "cycle", "writer", "stamp_ns", "due_ns"]
    follower_reads = [row for row in reads[1:] if row[0] == "follower"]
    assert summary.tasks["follower"].stale_reads == len(follower_reads)
    # before the plant's first cycle ended, all it had published were its initial outputs (stamp 0)
    first_end_cycle = (int(timing[0][4]) - int(timing[0][2])) // P
    before = [row for row in follower_reads if int(row[1]) < first_end_cycle]
    assert before, "the follower read while the plant had not started: stale reads"
    assert all(row[3] == "0" for row in before), "a read found no sample: the initial outputs were not there"
    assert min(int(row[1]) for row in follower_reads) >= 1, "the read at T0 is the LET one: the initial outputs"
    signals = _rows(tmp_path / "run" / "signals.csv")
    u0 = [signals[0].index("follower.u[0]"), signals[0].index("follower.u[1]")]
    assert [float(signals[1][i]) for i in u0] == INITIAL, "the follower read the initial outputs at T0"
    result = replay(tmp_path / "run", tmp_path / "replay", app=_app(name))
    assert result.equal, (result.cannot, result.divergence and result.divergence.describe())
    simulated = rtloop.simulate(_app(name), 1.0, tmp_path / "sim")
    assert simulated.tasks["follower"].stale_reads == 0
    assert _rows(tmp_path / "sim" / "signals.csv")[:2] == signals[:2], "the first row as in simulation"
