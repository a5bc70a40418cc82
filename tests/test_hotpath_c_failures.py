"""The C hot path on its failure paths and in what C allows (issue 29): a failed clock_nanosleep names
the call as the Python twin does, a failed allocation in add_input leaks nothing, and no double is
read through an integer lvalue."""

from __future__ import annotations

import gc
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from rtloop.errors import LibcError
from rtloop.ipc import hotpath
from rtloop.ipc.ring import Int64Ring
from rtloop.ipc.schema import constants, task_segment_size
from rtloop.ipc.segments import Segment, new_run_token
from rtloop.ipc.status import CONTROL_WORDS, STATUS_WORDS, WordBlock
from rtloop.ipc.wiring import TaskWiring, TaskWiringPlan
from rtloop.linux.rt import AbsoluteSleeper
from rtloop.runnable import TickInfo

SRC = Path(__file__).resolve().parent.parent / "src" / "rtloop"
needs_c = pytest.mark.skipif(not hotpath.c_built(), reason=f"the C hot path is not built: {hotpath.why_python()}")
WORDS = constants()
FAILED_SLEEP = r"clock_nanosleep\(CLOCK_MONOTONIC, TIMER_ABSTIME\) failed: Invalid argument \(errno 22\)"


def test_the_python_sleeper_names_the_failed_call() -> None:
    with pytest.raises(LibcError, match=FAILED_SLEEP):
        AbsoluteSleeper().sleep_until(-1_000_000_000)  # before the clock's epoch: EINVAL


@needs_c
def test_the_c_sleep_names_the_failed_call_as_its_twin_does() -> None:
    """It raised a bare OSError ("[Errno 22] Invalid argument"), naming no call."""
    from rtloop.ipc import _hotpath

    with pytest.raises(LibcError, match=FAILED_SLEEP):
        _hotpath.sleep_until(-1_000_000_000)


def test_a_cycle_whose_sleep_fails_raises_the_same_libc_error(hot_path: str) -> None:
    """The task loop's own sleep to the release (``Core.begin``) and its Python twin's."""
    token = new_run_token()
    control = Segment.create("hotpath", os.getpid(), token, "control", CONTROL_WORDS * 8)
    task = Segment.create("hotpath", os.getpid(), token, "task", task_segment_size(16))
    try:
        status = WordBlock(task, 0, STATUS_WORDS)
        timing = Int64Ring.initialise(task, 16, 4, STATUS_WORDS * 8)
        wiring = TaskWiring(TaskWiringPlan(), np.zeros(1), np.zeros(1), status)
        work = hotpath.cycle_work(TickInfo(), wiring, WordBlock(control, 0, CONTROL_WORDS), status, timing,
                                  1_000_000, False)
        work.start(-1_000_000_000, 1_000_000_000, 0)  # the first release lies before the clock's epoch
        with pytest.raises(LibcError, match=FAILED_SLEEP):
            work.begin()
        work.close()
    finally:
        for segment in (control, task):
            segment.close()
            segment.unlink()


@needs_c
def test_a_failed_allocation_in_add_input_leaks_nothing() -> None:
    """Each of add_input's allocations made to fail in turn (``_testcapi.set_nomemory``), on a fresh
    Core each time: the scratch allocated before a failed span table stayed allocated for good (the
    Core frees only the inputs it counted). Now nothing stays behind."""
    testcapi = pytest.importorskip("_testcapi", reason="this Python has no _testcapi to make allocations fail")
    from rtloop.ipc import _hotpath

    header = WORDS["HEADER_WORDS"]
    channel = np.zeros(header + 3 * (WORDS["SLOT_VALUES"] + 2), dtype=np.int64)
    channel[WORDS["CHANNEL_N_VALUES"]], channel[WORDS["CHANNEL_N_SLOTS"]] = 2, 3
    spans = ((0, 0, 2),)

    def core():
        timing = np.zeros(header + 16 * 4, dtype=np.int64)
        timing[WORDS["QUEUE_WIDTH"]], timing[WORDS["QUEUE_CAPACITY"]] = 4, 16
        return _hotpath.Core(TickInfo(), np.zeros(2), np.zeros(1), np.zeros(CONTROL_WORDS, dtype=np.int64),
                             np.zeros(STATUS_WORDS, dtype=np.int64), timing, 1_000_000, False)

    def sweep() -> int:
        failed = 0
        for fail_at in range(12):
            work = core()
            testcapi.set_nomemory(fail_at, fail_at + 1)  # only the fail_at-th allocation from here fails
            try:
                work.add_input(channel, 1_000_000, 0, 2, spans)
            except MemoryError:
                failed += 1
            finally:
                testcapi.remove_mem_hooks()
            work.close()
            del work
        return failed

    sweep()
    sweep()  # caches and free lists warmed up
    # One full collection before counting and one after (not one per sweep: in the whole suite's
    # process, with its large heap, each took ~0.4 s); whatever garbage the sweeps left meanwhile
    # is freed by the second before the blocks are counted again.
    gc.collect()
    before = sys.getallocatedblocks()
    failures = sum(sweep() for _ in range(20))
    gc.collect()
    leaked = sys.getallocatedblocks() - before
    assert failures >= 20  # add_input's own allocations did fail
    assert leaked < 5, f"{leaked} memory blocks left behind by 20 sweeps of failed allocations"


def test_no_double_is_read_through_an_integer_lvalue() -> None:
    """``(int64_t *)self->y`` read the outputs' doubles through int64_t lvalues: undefined behaviour
    under C's strict aliasing (the build does not pass -fno-strict-aliasing), which lets the compiler
    reorder or drop those reads. A double's bits are copied with memcpy instead."""
    for path in (SRC / "ipc" / "_hotpath.c", SRC / "io" / "_devio.c"):
        text = path.read_text()
        doubles = {name for declaration in re.findall(r"\bdouble\s*(\*[^;=(){}]*)", text)  # double *u, *y;
                   for name in re.findall(r"\*\s*(\w+)", declaration)}
        casts = re.findall(r"\(\s*(?:const\s+)?(?:u?int(?:8|16|32|64)_t|long long|long|int|aword)\s*\*\s*\)\s*"
                           r"(?:\w+->)?(\w+)\b", text)
        punned = sorted({name for name in casts if name in doubles})
        assert not punned, f"{path.name}: doubles read through integer pointers: {punned}"
