"""One shared-memory schema: the C header is generated from it, the built extension and the
Python classes agree with it word for word, and both hot paths keep the same timeline."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rtloop.ipc import hotpath, schema
from rtloop.ipc.channels import LatestValue, LetChannel
from rtloop.ipc.ring import Int64Ring, SampleQueue
from rtloop.ipc.schema import (
    CONTROL_WORDS,
    HEADER_WORDS,
    NO_STAMP,
    STATUS_WORDS,
    TASK_TIMING_OFFSET_BYTES,
    TIMING_RECORD_WORDS,
    ChannelWord,
    ControlWord,
    PortWord,
    QueueWord,
    SlotWord,
    StatusWord,
    TimingField,
)
from rtloop.ipc.segments import Segment, new_run_token
from rtloop.ipc.status import WordBlock
from rtloop.ipc.wiring import TaskWiring, TaskWiringPlan
from rtloop.runnable import TickInfo

HEADER = Path(schema.__file__).with_name("_schema.h")
needs_c = pytest.mark.skipif(not hotpath.c_built(), reason=f"the C hot path is not built: {hotpath.why_python()}")
P = 1_000_000


def test_the_c_header_is_generated_from_the_schema() -> None:
    assert HEADER.read_text() == schema.c_header(), "regenerate: python -m rtloop.ipc.schema > " + str(HEADER)


@needs_c
def test_the_built_extension_agrees_with_every_constant_of_the_schema() -> None:
    from rtloop.ipc import _hotpath

    assert schema.constants() == _hotpath.SCHEMA
    assert len(schema.constants()) > 40  # every word of every block, not a sample


def test_an_extension_built_from_another_schema_is_not_used(tmp_path: Path) -> None:
    code = ("import rtloop.ipc.schema as s; real = s.constants; "
            "s.constants = lambda: {**real(), 'STATUS_CYCLE': 99}; "
            "from rtloop.ipc import hotpath; print(hotpath.hot_path()); print(hotpath.why_python())")
    env = {**os.environ}
    env.pop(hotpath.PURE_PYTHON_ENV, None)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    kind, reason = result.stdout.splitlines()
    assert kind == "python"
    assert "STATUS_CYCLE" in reason if hotpath.c_built() else "not built" in reason


def test_every_header_word_fits_its_block() -> None:
    assert max(ControlWord) < CONTROL_WORDS and max(StatusWord) < STATUS_WORDS
    for block in (QueueWord, ChannelWord, PortWord):
        assert max(block) < HEADER_WORDS, block
    assert TIMING_RECORD_WORDS == len(TimingField) == len(schema.TIMING_RECORD.names)
    assert schema.task_segment_size(10) == STATUS_WORDS * 8 + (HEADER_WORDS + 10 * TIMING_RECORD_WORDS) * 8


def test_the_python_classes_write_the_words_the_schema_names(tmp_path: Path) -> None:
    token = new_run_token()
    size = LetChannel.size_bytes(3, 2) + LatestValue.size_bytes(2) + SampleQueue.size_bytes(2, 4) + \
        Int64Ring.size_bytes(4, TIMING_RECORD_WORDS)
    segment = Segment.create("schema", os.getpid(), token, "all", size)
    try:
        offsets = np.cumsum([0, LetChannel.size_bytes(3, 2), LatestValue.size_bytes(2), SampleQueue.size_bytes(2, 4)])
        channel = LetChannel.initialise(segment, 3, 2, int(offsets[0]))
        port = LatestValue.initialise(segment, np.array([1.0, 2.0]), int(offsets[1]), fed_by_profile=True)
        queue = SampleQueue.initialise(segment, 2, 4, int(offsets[2]))
        ring = Int64Ring.initialise(segment, 4, TIMING_RECORD_WORDS, int(offsets[3]))
        words = np.frombuffer(segment.buffer, dtype=np.int64)

        def word(offset: np.int64, index: int) -> int:
            return int(words[int(offset) // 8 + index])

        channel.publish(123, np.array([4.0, 5.0, 6.0]))
        assert word(offsets[0], ChannelWord.PUBLISHED) == 1 and word(offsets[0], ChannelWord.N_VALUES) == 3
        assert word(offsets[0], ChannelWord.N_SLOTS) == 2
        slot0, slot1 = HEADER_WORDS, HEADER_WORDS + SlotWord.VALUES + 3
        assert word(offsets[0], slot0 + SlotWord.SEQ) == 2 and word(offsets[0], slot0 + SlotWord.STAMP_NS) == 123
        assert word(offsets[0], slot1 + SlotWord.STAMP_NS) == NO_STAMP
        assert np.frombuffer(segment.buffer, np.float64)[int(offsets[0]) // 8 + slot0 + SlotWord.VALUES] == 4.0
        port.write(np.array([7.0, 8.0]))
        assert word(offsets[1], PortWord.SEQ) == 2 and word(offsets[1], PortWord.WRITES) == 1
        assert word(offsets[1], PortWord.N_VALUES) == 2 and word(offsets[1], PortWord.FED_BY_PROFILE) == 1
        assert np.frombuffer(segment.buffer, np.float64)[int(offsets[1]) // 8 + HEADER_WORDS + 1] == 8.0
        queue.push(9, np.array([1.0, 2.0]))
        assert word(offsets[2], QueueWord.WRITTEN) == 1 and word(offsets[2], QueueWord.WIDTH) == 2
        assert word(offsets[2], QueueWord.CAPACITY) == 4 and word(offsets[2], HEADER_WORDS) == 9  # ticks first
        ring.push4(1, 2, 3, 4)
        assert word(offsets[3], QueueWord.WRITTEN) == 1 and word(offsets[3], QueueWord.WIDTH) == TIMING_RECORD_WORDS
        record = ring.drain().view(schema.TIMING_RECORD)[0, 0]
        assert (record["cycle"], record["release_ns"], record["start_ns"], record["end_ns"]) == (1, 2, 3, 4)
        assert word(offsets[3], QueueWord.READ) == 1
        del channel, port, queue, ring
    finally:
        segment.close()
        segment.unlink()


# --- both twins, one clock: the skip / catch-up / max-misses logic cycle by cycle ------------------

def _twin(kind: str, catch_up: bool, max_misses: int | None, made: list[Segment]):
    token = new_run_token()
    control_segment = Segment.create("twins", os.getpid(), token, f"control{kind}", CONTROL_WORDS * 8)
    task_segment = Segment.create("twins", os.getpid(), token, f"task{kind}", schema.task_segment_size(64))
    made += [control_segment, task_segment]
    status = WordBlock(task_segment, 0, STATUS_WORDS)
    timing = Int64Ring.initialise(task_segment, 64, TIMING_RECORD_WORDS, TASK_TIMING_OFFSET_BYTES)
    wiring = TaskWiring(TaskWiringPlan(), np.zeros(0), np.zeros(0), status)
    make = hotpath.compiled_cycle if kind == "c" else hotpath.PythonCycle
    work = make(TickInfo(), wiring, WordBlock(control_segment, 0, CONTROL_WORDS), status, timing, P, catch_up,
                max_misses)
    return work, status, timing


# (start, end) of each cycle after its release, in periods: late starts, overruns of 1.5 and 3.2
# periods, a run of misses, an exact-deadline finish.
SCRIPT = [(0.1, 0.3), (0.2, 1.5), (0.0, 0.2), (0.5, 3.2), (0.1, 0.4), (0.0, 1.0), (0.3, 1.2), (0.2, 1.1),
          (0.9, 1.9), (0.1, 0.2), (0.0, 0.9), (2.5, 2.6), (0.1, 0.3)]


@needs_c
@pytest.mark.parametrize("catch_up", [False, True], ids=["skip", "catch_up"])
@pytest.mark.parametrize("max_misses", [None, 3])
def test_both_twins_keep_the_same_timeline_cycle_by_cycle(catch_up: bool, max_misses: int | None) -> None:
    made: list[Segment] = []
    try:
        runs = {}
        for kind in ("c", "python"):
            work, status, timing = _twin(kind, catch_up, max_misses, made)
            t0 = 10 * P
            work.start(t0, t0 + 40 * P, 0)
            trace = []
            for start, end in SCRIPT:
                release = work.release_ns
                began = work.begin_at(release + round(start * P))
                if not began:
                    trace.append(("stopped",))
                    break
                went_on = work.finish_at(release + round(end * P))
                trace.append((began, went_on, status[StatusWord.OVERRUNS], status[StatusWord.DEADLINE_MISSES],
                               status[StatusWord.MISSES_IN_A_ROW_MAX], status[StatusWord.CYCLE]))
            runs[kind] = (trace, timing.drain().tolist())
            work.close()
        assert runs["c"] == runs["python"]
        trace, records = runs["python"]
        assert any(not went_on for _, went_on, *_ in trace) == (max_misses is not None)
        cycles = [record[TimingField.CYCLE] for record in records]
        assert (cycles == list(range(len(cycles)))) == catch_up, cycles  # skip leaves gaps in the cycles
    finally:
        for segment in made:
            segment.unlink()



@pytest.mark.parametrize("kind", ["c", "python"])
@pytest.mark.parametrize("catch_up", [False, True], ids=["skip", "catch_up"])
def test_releases_after_the_runs_end_are_no_overruns(kind: str, catch_up: bool) -> None:
    """A run of releases 0-4: cycle 2 ends 1.5 periods late (release 3, inside the run, is an
    overrun), cycle 4 ends 2.5 periods late (releases 5 and 6 lie past the run's end: no overruns)."""
    if kind == "c" and not hotpath.c_built():
        pytest.skip(f"the C hot path is not built: {hotpath.why_python()}")
    made: list[Segment] = []
    try:
        work, status, _ = _twin(kind, catch_up, None, made)
        t0 = 10 * P
        work.start(t0, t0 + 5 * P, 0)
        while work.begin_at(work.release_ns):
            cycle = (work.release_ns - t0) // P
            work.finish_at(work.release_ns + {2: round(1.5 * P), 4: round(2.5 * P)}.get(cycle, P // 5))
        assert status[StatusWord.DEADLINE_MISSES] == 2
        assert status[StatusWord.OVERRUNS] == 1
        work.close()
    finally:
        for segment in made:
            segment.unlink()


@needs_c
def test_a_compiled_cycle_left_in_a_reference_cycle_is_collected_without_a_crash(tmp_path: Path) -> None:
    """An exception's traceback can keep a task's hot path in a reference cycle with the views it
    holds; the collector used to clear a memoryview before the hot path released its export of it,
    and the process died with SIGSEGV (pytest showed it while formatting a failure)."""
    script = tmp_path / "cycle.py"
    script.write_text(
        "import gc, sys\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from test_schema import P, _twin\n"
        "made = []\n"
        "work, status, timing = _twin('c', False, None, made)\n"
        "work.start(10 * P, 15 * P, 0)\n"
        "for segment in made:\n"
        "    segment.unlink()\n"
        "garbage = [work, status, timing, made]\n"
        "garbage.append(garbage)\n"
        "del work, status, timing, made, garbage\n"
        "gc.collect()\n"
        "print('collected')\n")
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout == "collected\n", (result.returncode, result.stderr[-2000:])


def test_the_built_extension_carries_the_digest_of_its_sources() -> None:
    from rtloop import build_check
    from rtloop.ipc import _hotpath

    here = build_check.sources_digest(Path(hotpath.__file__).resolve().parent, hotpath.SOURCES)
    assert here is not None and here == _hotpath.SOURCES_DIGEST


def test_an_extension_older_than_its_sources_is_not_used(tmp_path: Path) -> None:
    """Before: only the schema was compared, so a build older than _hotpath.c (same schema, another
    signature) was used, and a task failed with ``TypeError: Core.set_record() takes exactly one argument``."""
    code = ("from rtloop import build_check; build_check.sources_digest = lambda folder, names: 'changed!'\n"
            "from rtloop.ipc import hotpath; print(hotpath.hot_path()); print(hotpath.why_python())")
    env = {**os.environ}
    env.pop(hotpath.PURE_PYTHON_ENV, None)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    kind, reason = result.stdout.splitlines()
    assert kind == "python"
    assert "built from other sources" in reason and "pip install -e ." in reason
