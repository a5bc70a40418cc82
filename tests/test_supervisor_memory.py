"""The supervisor's resident size stays what it uses (issue 30, defect 11).

A 95 s soak grew the supervisor's resident memory by 2.7 MB. tracemalloc snapshots in a soak
(benchmarks/bench_supervisor_memory.py) found no Python object that kept growing (a few hundred
KiB between snapshots, buffers that are flushed); /proc's parts of VmRSS found the growth: RssShmem,
the run's shared-memory segments, whose pages the supervisor touched one by one as the rings and
queues filled (bounded by their size, no memory taken from the machine), and some freed heap glibc
kept. The segments the supervisor creates are now mapped whole (MAP_POPULATE), and the free heap goes
back to the kernel at every summary rewrite (``linux/memory.py:give_back_free_heap``).
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name
from rt_test_runnables import Counter
from rtloop.linux.memory import give_back_free_heap, resident_bytes
from rtloop.runtime.session import Limits

GLIBC = getattr(ctypes.CDLL(None), "malloc_trim", None) is not None


@pytest.mark.skipif(not GLIBC, reason="malloc_trim is glibc's: another C library keeps its own ways")
def test_freed_memory_goes_back_to_the_kernel() -> None:
    kept, freed = [], []
    for i in range(40_000):  # 64 B to 16 KiB: the heap, not mmap; every other block stays, so the heap cannot shrink
        (kept if i % 64 == 0 else freed).append(bytearray(64 + (i * 397) % 16_384))
    before = resident_bytes()
    freed.clear()
    held = resident_bytes()
    assert give_back_free_heap()
    after = resident_bytes()
    assert before is not None and held is not None and after is not None
    assert held - after > 64 << 20, (before, held, after)  # most of the ~300 MiB freed was still resident
    assert len(kept) == 625


def _shmem_kib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssShmem:"):
            return int(line.split()[1])
    raise AssertionError("no RssShmem in /proc/self/status")


def test_a_segment_the_run_creates_is_resident_whole_from_the_start() -> None:
    from rtloop.ipc.segments import Segment, new_run_token

    before = _shmem_kib()
    segment = Segment.create(unique_name("populate"), os.getpid(), new_run_token(), "ring", 16 << 20)
    try:
        assert _shmem_kib() - before >= 15 << 10  # 16 MiB mapped, not one page touched by this process
    finally:
        segment.unlink()
        segment.close()


def test_every_summary_rewrite_gives_the_free_heap_back(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    from rtloop.runtime import session

    calls: list[int] = []
    monkeypatch.setattr(session, "give_back_free_heap", lambda: calls.append(1) or True)
    app = rtloop.App(unique_name("trim"))
    app.add_task("count", Counter(), period_ns=1_000_000, policy="other")
    rtloop.run(app, 1.0, tmp_path / "run", limits=Limits(summary_interval_s=0.1))
    assert len(calls) >= 3, calls
