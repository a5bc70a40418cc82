"""The supervisor's share of a core while a 4-task app at 20 kHz records everything, beside references.

    tools/as-root .venv/bin/python benchmarks/bench_supervisor_load.py [--duration S] [--tasks N] [--rate HZ]

Each task is a ``Counter``-like runnable with ``--width`` outputs, all recorded (timing.csv,
signals.csv and run.mcap when the ``ros`` extra is installed). Tasks run at SCHED_FIFO where
allowed, spread over the processors. The supervisor is this process: its CPU time
(``time.process_time``, user + system, this process only, not the tasks) is sampled at the
first and the last progress callback, so start-up and the final flush are left out; the share
of a core is CPU seconds per second of run time. In the same run, as references: the same app
recording no signals (what the supervisor costs with the timing records only), and numpy's
``tofile`` of the same bytes the full run drained (the floor of any recording).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import rtloop
from rtloop import App, Runnable


class Counting(Runnable):
    """y[0] = steps so far, y[1..] = the tick's time in seconds times 1..width-1 (recorded values that change)."""

    def __init__(self, width: int) -> None:
        self.n_inputs, self.n_outputs = 0, width
        self.count = 0

    def step(self, u: np.ndarray, y: np.ndarray) -> None:
        self.count += 1
        y[0] = self.count
        y[1:] = self.tick.time_s


def make_app(name: str, tasks: int, rate_hz: int, width: int, record: bool) -> App:
    app = App(name)
    cpus = sorted(os.sched_getaffinity(0))
    for i in range(tasks):
        task = app.add_task(f"t{i}", Counting(width), period_ns=round(1e9 / rate_hz), priority=80 - i,
                            cpu=cpus[i % len(cpus)])
        if record:
            app.record(task.y)
    return app


def locked_kib(pid: int | str) -> int:
    """VmLck of a process (memory it locked, kB)."""
    try:
        with open(f"/proc/{pid}/status") as status:
            return next(int(line.split()[1]) for line in status if line.startswith("VmLck:"))
    except (OSError, StopIteration):
        return -1


def task_pids(name: str) -> list[int]:
    """The task processes of this process's running app ``name``, from the app's own registry (each
    task's status block holds its pid, however the process was started)."""
    from rtloop.ipc.ports import running_apps

    return [pid for app in running_apps() if app.name == name and app.pid == os.getpid()
            for pid in app.task_pids().values() if pid]


def measure(app: App, duration_s: float, out: Path) -> dict[str, float]:
    samples: list[tuple[float, float]] = []
    locked: dict[str, int] = {}

    def progress(state: object) -> None:
        samples.append((time.monotonic(), time.process_time()))
        if len(samples) == 20:  # the tasks are in their loops by now
            locked["supervisor_vmlck_kib"] = locked_kib("self")
            locked["task_vmlck_kib_max"] = max((locked_kib(pid) for pid in task_pids(app.name)), default=-1)

    summary = rtloop.run(app, duration_s, out, trim=0, on_progress=progress)
    (wall0, cpu0), (wall1, cpu1) = samples[0], samples[-1]
    summary_json = json.loads((out / "summary.json").read_text())
    lost = summary_json["recording"]["lost"]
    cycles = sum(task.timing.cycles for task in summary.tasks.values())
    return {"core_share": (cpu1 - cpu0) / (wall1 - wall0), "cycles_recorded": cycles,
            "records_lost": sum(sum(per_task.values()) for per_task in lost.values()),
            "misses": sum(task.timing.deadline_misses for task in summary.tasks.values()),
            "run_mcap": (out / "run.mcap").exists(), **locked}


def tofile_share(cycles: int, width: int, duration_s: float, folder: Path) -> float:
    """CPU seconds numpy takes to write the run's timing records and signal rows raw, per second of run."""
    timing = np.zeros((cycles, 4), dtype=np.int64)
    signals = np.zeros((cycles, 1 + width), dtype=np.float64)
    started = time.process_time()
    with open(folder / "raw.bin", "wb") as file:
        for block in range(0, cycles, 4096):
            timing[block:block + 4096].tofile(file)
            signals[block:block + 4096].tofile(file)
    return (time.process_time() - started) / duration_s


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--tasks", type=int, default=4)
    parser.add_argument("--rate", type=int, default=20_000, help="each task's rate, Hz")
    parser.add_argument("--width", type=int, default=4, help="recorded outputs per task")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, record in (("everything recorded", True), ("timing only (no signals)", False)):
            app = make_app(f"bench_supervisor_{os.getpid()}_{int(record)}", args.tasks, args.rate, args.width, record)
            results[label] = measure(app, args.duration, Path(tmp) / label.split()[0])
        cycles = results["everything recorded"]["cycles_recorded"]
        results["numpy tofile of the same bytes"] = {"core_share": tofile_share(cycles, args.width, args.duration,
                                                                                Path(tmp))}
    print(f"supervisor load: {args.tasks} tasks at {args.rate} Hz, {args.width} recorded values each, "
          f"{args.duration:g} s, load average {os.getloadavg()[0]:.1f}")
    print("| what | supervisor, share of one core | cycles recorded | lost | misses | run.mcap | VmLck kB: "
          "supervisor, task (max) |")
    print("|---|---|---|---|---|---|---|")
    for label, r in results.items():
        print(f"| {label} | {r['core_share']:.3f} | {r.get('cycles_recorded', '')} | {r.get('records_lost', '')} | "
              f"{r.get('misses', '')} | {r.get('run_mcap', '')} | {r.get('supervisor_vmlck_kib', '')}, "
              f"{r.get('task_vmlck_kib_max', '')} |")
    if args.json is not None:
        settings = {k: str(v) for k, v in vars(args).items() if k != "json"}  # not where it was written
        args.json.write_text(json.dumps({"args": settings, "results": results}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
