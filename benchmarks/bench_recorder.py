"""Recorder throughput: timing records and signal rows per second, beside numpy's ``tofile`` of the same bytes.

    .venv/bin/python benchmarks/bench_recorder.py [--records N] [--tasks N] [--width N] [--mcap]

What the supervisor's drain hands the recorder, block by block (4096 records per task, as
``RunSession.drain`` does): ``add_timing`` + ``flush`` for timing records (statistics,
timing.csv, and run.mcap with ``--mcap``), ``add_signals`` + ``flush`` for signal rows
(signals.csv, run.mcap). The reference, in the same run on the same data: the same int64 /
float64 blocks written raw with ``ndarray.tofile`` (the floor any text format sits above).
One core: everything runs in this process, timed by its CPU time (time.process_time), so a busy
machine slows the wall clock, not the figures.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rtloop import App, Runnable
from rtloop.record.recorder import Recorder

BLOCK = 4096


class Outputs(Runnable):
    """A runnable with ``n`` outputs (only its shape matters here)."""

    def __init__(self, n: int) -> None:
        self.n_inputs, self.n_outputs = 0, n

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        pass


def make_app(tasks: int, width: int) -> App:
    app = App("bench_recorder")
    for i in range(tasks):
        task = app.add_task(f"t{i}", Outputs(width), period_ns=50_000, policy="other")
        app.record(task.y)
    return app


def timing_blocks(records: int, tasks: int) -> list[tuple[str, np.ndarray]]:
    """Per task, blocks of (cycle, release, start, end) as a 20 kHz task would record them."""
    blocks = []
    per_task = records // tasks
    for start in range(0, per_task, BLOCK):
        cycles = np.arange(start, min(start + BLOCK, per_task), dtype=np.int64)
        release = 1_000_000_000 + cycles * 50_000
        table = np.column_stack((cycles, release, release + 12_345, release + 31_416))
        blocks += [(f"t{i}", table) for i in range(tasks)]
    return blocks


def signal_blocks(rows: int, tasks: int, width: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(1)
    blocks = []
    per_task = rows // tasks
    for start in range(-1, per_task - 1, BLOCK):
        ticks = np.arange(start, min(start + BLOCK, per_task - 1), dtype=np.int64)
        values = rng.standard_normal((ticks.size, width)) * 1e3
        blocks += [(f"t{i}", ticks, values) for i in range(tasks)]
    return blocks


def time_recorder(app: App, folder: Path, mcap: bool, feed) -> float:
    recorder = Recorder(app, folder, trim=0)
    if mcap:
        recorder.start(1_000_000_000, 1_700_000_000_000_000_000)
    started = time.process_time()
    feed(recorder)
    recorder.flush(final=True)
    recorder.close()
    elapsed = time.process_time() - started
    if recorder.stopped or (mcap and recorder.mcap_note):
        sys.exit(f"bench_recorder: {recorder.stopped or recorder.mcap_note}")
    return elapsed


def time_tofile(folder: Path, arrays: list[np.ndarray]) -> float:
    started = time.process_time()
    with open(folder / "raw.bin", "wb") as file:
        for array in arrays:
            array.tofile(file)
    return time.process_time() - started


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=int, default=1_000_000, help="timing records and signal rows in all")
    parser.add_argument("--tasks", type=int, default=4)
    parser.add_argument("--width", type=int, default=4, help="recorded values per task")
    parser.add_argument("--mcap", action="store_true", help="also write run.mcap (needs the ros extra)")
    parser.add_argument("--json", type=Path, default=None, help="write the results here too")
    args = parser.parse_args(argv)
    app = make_app(args.tasks, args.width)
    timing = timing_blocks(args.records, args.tasks)
    signals = signal_blocks(args.records, args.tasks, args.width)
    n_timing = sum(len(b) for _, b in timing)
    n_signals = sum(len(t) for _, t, _ in signals)

    def feed_timing(recorder: Recorder) -> None:
        for task, block in timing:
            recorder.add_timing(task, block)
            recorder.flush()

    def feed_signals(recorder: Recorder) -> None:
        for task, ticks, values in signals:
            recorder.add_signals(task, ticks, values)
            recorder.flush()

    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for what, feed, count, arrays in (
            ("timing records", feed_timing, n_timing, [b for _, b in timing]),
            ("signal rows", feed_signals, n_signals, [np.column_stack((t, v)) for _, t, v in signals]),
        ):
            folder = Path(tmp) / what.replace(" ", "_")
            folder.mkdir()
            recorder_s = time_recorder(app, folder, args.mcap, feed)
            raw_s = time_tofile(folder, arrays)
            results[what] = {"count": count, "recorder_per_s": count / recorder_s, "tofile_per_s": count / raw_s,
                             "recorder_s": recorder_s, "tofile_s": raw_s}
    print(f"recorder throughput: {args.tasks} tasks × {args.width} values, blocks of {BLOCK}, "
          f"run.mcap {'on' if args.mcap else 'off'}")
    print("| what | count | recorder /s | numpy tofile /s | recorder ÷ tofile |")
    print("|---|---|---|---|---|")
    for what, r in results.items():
        print(f"| {what} | {r['count']} | {r['recorder_per_s']:,.0f} | {r['tofile_per_s']:,.0f} | "
              f"{r['recorder_per_s'] / r['tofile_per_s']:.3f} |")
    if args.json is not None:
        settings = {k: v for k, v in vars(args).items() if k != "json"}  # not where it was written
        args.json.write_text(json.dumps({"args": settings, "results": results}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
