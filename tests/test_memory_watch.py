"""The supervisor watches each task's resident memory while it runs: a step that leaks a reference
cycle every cycle (the collector is off in a task) is said in a note, with the growth and its rate."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import rtloop
from rtloop.runtime.memory_watch import GROWTH_NOTE_BYTES, MemoryWatch, resident_bytes
from rtloop.runtime.session import Limits


class LeaksCycles(rtloop.Runnable):
    """Keeps nothing on purpose: each step makes a 256 kB buffer that a reference cycle keeps alive."""

    n_inputs, n_outputs = 0, 1

    def step(self, u, y) -> None:
        node: dict = {"buffer": bytearray(256 * 1024)}
        node["self"] = node  # a cycle: freed only by the collector, which is off in a task
        y[0] = len(node)


class Clean(rtloop.Runnable):
    n_inputs, n_outputs = 0, 1

    def step(self, u, y) -> None:
        y[0] = len(bytearray(256 * 1024))  # freed at once: no cycle


def test_resident_bytes_of_this_process_and_of_none() -> None:
    assert (resident_bytes(os.getpid()) or 0) > 1_000_000
    assert resident_bytes(2**22 + 12345) is None


def test_the_watch_notes_growth_beyond_its_bound_only() -> None:
    watch = MemoryWatch()
    watch.sample("flat", 1, 0)
    watch.samples["flat"].first_bytes = watch.samples["flat"].max_bytes = 100 << 20
    watch.samples["grows"] = type(watch.samples["flat"])(100 << 20, 0, 200 << 20, 10_000_000_000, 200 << 20)
    notes = watch.notes()
    assert len(notes) == 1 and notes[0].startswith("task grows's memory grew 100 MiB in 10 s (10 MiB/s)")
    assert watch.to_json("grows") == {"first": 100 << 20, "last": 200 << 20, "max": 200 << 20}


@pytest.mark.rt
def test_a_step_leaking_reference_cycles_is_noted_a_clean_one_is_not(tmp_path: Path) -> None:
    pid = os.getpid()
    app = rtloop.App(f"memwatch_{pid}")
    app.add_task("leaky", LeaksCycles(), period_ns=5_000_000, priority=10)  # 200 Hz × 256 kB ≈ 50 MB/s
    app.add_task("clean", Clean(), period_ns=5_000_000, priority=10)
    summary = rtloop.run(app, 3.0, tmp_path / "run", limits=Limits(summary_interval_s=0.25))
    leaky, clean = summary.tasks["leaky"].resident_bytes, summary.tasks["clean"].resident_bytes
    assert leaky is not None and clean is not None
    assert leaky["max"] - leaky["first"] > GROWTH_NOTE_BYTES, leaky
    assert clean["max"] - clean["first"] < GROWTH_NOTE_BYTES, clean
    grown = [note for note in summary.notes if "memory grew" in note]
    assert len(grown) == 1 and grown[0].startswith("task leaky's memory grew"), summary.notes
