"""What a write to an input port costs a client: a held ``PortWriter`` (the segment mapped once)
against ``RunningApp.write`` (the segment mapped and unmapped for every value, as every write did
before the writer existed). The ROS 2 talker and the Foxglove inputs write through a held writer.

The app's segments and registry are made as a live run makes them (``AppLayout.create``); no task
runs, so what is timed is the client's side only. Blocks of the two ways alternate in one run, and
each block's time per write is reported; the median of the blocks is the figure.

Usage::

    python benchmarks/bench_port_writer.py --writes 2000 --rounds 5
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from rt_test_runnables import Gain
from rtloop.app.builder import App
from rtloop.ipc.ports import connect_app
from rtloop.runtime.layout import AppLayout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--writes", type=int, default=2000, help="writes per block")
    parser.add_argument("--rounds", type=int, default=5, help="blocks of each way, alternating")
    args = parser.parse_args()
    app = App(f"bench_writer_{os.getpid()}")
    task = app.add_task("g", Gain(1), period_ns=1_000_000)
    app.port("setpoint", to=task.u[0])
    layout = AppLayout.create(app)
    try:
        running = connect_app(app.name)
        per_write_us: dict[str, list[float]] = {"held PortWriter": [], "RunningApp.write (map per write)": []}
        values = [0.5]
        for _ in range(args.rounds):
            with running.writer("setpoint") as writer:
                start = time.perf_counter_ns()
                for _ in range(args.writes):
                    writer.write(values)
                per_write_us["held PortWriter"].append((time.perf_counter_ns() - start) / args.writes / 1e3)
            start = time.perf_counter_ns()
            for _ in range(args.writes):
                running.write("setpoint", values)
            per_write_us["RunningApp.write (map per write)"].append(
                (time.perf_counter_ns() - start) / args.writes / 1e3)
        for way, blocks in per_write_us.items():
            print(f"{way:34s} median {statistics.median(blocks):7.2f} µs per write "
                  f"(blocks: {', '.join(f'{b:.2f}' for b in blocks)})")
    finally:
        layout.close()


if __name__ == "__main__":
    main()
