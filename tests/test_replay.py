"""Replay of a whole run: the read log (stale reads), the real timeline, divergence reports."""

from __future__ import annotations

import os

import numpy as np

from rtloop.ipc import hotpath
from rtloop.ipc.channels import NO_STAMP, LetChannel
from rtloop.ipc.segments import RecordRing, Segment, new_run_token
from rtloop.ipc.status import CONTROL_WORDS, STATUS_WORDS, StatusWord, WordBlock
from rtloop.runnable import TickInfo
from rtloop.runtime.task import task_segment_size
from rtloop.runtime.wiring import READ_LOG_WIDTH, InputLink, TaskWiring, TaskWiringPlan

P = 1_000_000
T0 = 5_000_000_000


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
        log = Segment.create("readlog", pid, token, "reads", RecordRing.size_bytes(16, READ_LOG_WIDTH))
        control = Segment.create("readlog", pid, token, "control", CONTROL_WORDS * 8)
        task = Segment.create("readlog", pid, token, "task", task_segment_size(16))
        made += [fast, slow, log, control, task]
        writers = [LetChannel.initialise(fast, 2, 4), LetChannel.initialise(slow, 2, 4)]
        RecordRing.initialise(log, 16, READ_LOG_WIDTH)
        status = WordBlock(task, 0, STATUS_WORDS)
        timing = RecordRing.initialise(task, 16, 4, STATUS_WORDS * 8)
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
            records = RecordRing(log).drain().tolist()
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
            Segment.create("readlog0", pid, token, "reads", RecordRing.size_bytes(4, READ_LOG_WIDTH))]
    try:
        LetChannel.initialise(made[0], 1, 2)
        RecordRing.initialise(made[1], 4, READ_LOG_WIDTH)
        plan = TaskWiringPlan(inputs=(InputLink(made[0].name, slice(0, 1), slice(0, 1), P, "a"),),
                              read_log=made[1].name, segments=(made[0].name, made[1].name))
        wiring = TaskWiring(plan, np.zeros(1), np.zeros(0), None)
        wiring.t0_ns = T0
        wiring.read_inputs(T0 + 3 * P, wiring.u)
        assert RecordRing(made[1]).drain().tolist() == [[3 * P, 0, NO_STAMP, 3 * P]]
    finally:
        for segment in made:
            segment.unlink()
