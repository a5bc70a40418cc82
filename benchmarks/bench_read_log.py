"""The cost of the read log (replay's record of stale reads) per cycle: with it, and as before it, in one run.

A task with connections logs each read that did not get the sample logical execution time
promised (``reads.csv``). Its promise is nothing extra in a clean cycle, one 4-word
record in a faulty one. Measured here, in one process pinned to a CPU under SCHED_FIFO,
for the compiled hot path and its Python twin, with the log attached and without it (a
task without the log is what every task was before it):

1. ``read_inputs`` of 1 and 4 connections in a clean cycle (every writer published the
   sample due) and in a stale one (every writer is one period late: a record per read);
2. the whole no-op iteration ``begin(); step(u, y); finish()`` of a task with one clean
   connection, releases in the past (``clock_nanosleep`` returns at once);
3. a ``--keep`` snapshot (``snapshot.take``, once per recording segment, in the loop) of
   JIWY's Python controller, of the JIWY plant FMU and of the 20-sim C++ and ANSI-C JIWY
   plants (built with gcc/g++ if there are).

Figures are medians of 11 batches (µs per call); the ring is drained between batches.

Usage (as root)::

    python benchmarks/bench_read_log.py
    python benchmarks/bench_read_log.py --repeats 4000 --json read_log.json
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (
    NoOp,
    add_output_options,
    facts_markdown,
    machine_facts,
    markdown_table,
    median_us_per_call,
    print_and_save,
)

from rtloop.ipc import hotpath
from rtloop.ipc.channels import LetChannel
from rtloop.ipc.ring import Int64Ring
from rtloop.ipc.schema import task_segment_size
from rtloop.ipc.segments import Segment, new_run_token
from rtloop.ipc.status import CONTROL_WORDS, STATUS_WORDS, WordBlock
from rtloop.ipc.wiring import READ_LOG_WIDTH, InputLink, TaskWiring, TaskWiringPlan
from rtloop.linux import rt
from rtloop.runnable import TickInfo

P = 1_000
RING = 1 << 16


class Rig:
    def __init__(self, n_writers: int) -> None:
        self.token, self.made = new_run_token(), []
        self.writers = [self._make(f"w{i}", LetChannel.size_bytes(1, 8)) for i in range(n_writers)]
        self.channels = [LetChannel.initialise(w, 1, 8) for w in self.writers]
        for channel in self.channels:  # samples stamped 0 and P: a read at P is clean, one at 2P is stale
            channel.publish(0, np.array([1.0]))
            channel.publish(P, np.array([2.0]))

    def _make(self, what: str, size: int) -> Segment:
        segment = Segment.create("bench_readlog", os.getpid(), self.token, what, size)
        self.made.append(segment)
        return segment

    def task(self, kind: str, n_inputs: int, with_log: bool) -> tuple[Any, Int64Ring | None, Int64Ring]:
        """The per-cycle work of a reader of the first ``n_inputs`` writers (C or Python)."""
        log = self._make(f"log{len(self.made)}", Int64Ring.size_bytes(RING, READ_LOG_WIDTH)) if with_log else None
        if log is not None:
            Int64Ring.initialise(log, RING, READ_LOG_WIDTH)
        control = self._make(f"control{len(self.made)}", CONTROL_WORDS * 8)
        segment = self._make(f"task{len(self.made)}", task_segment_size(RING))
        status = WordBlock(segment, 0, STATUS_WORDS)
        timing = Int64Ring.initialise(segment, RING, 4, STATUS_WORDS * 8)
        plan = TaskWiringPlan(
            inputs=tuple(InputLink(w.name, slice(0, 1), slice(i, i + 1), P, f"w{i}")
                         for i, w in enumerate(self.writers[:n_inputs])),
            read_log=log.name if log is not None else None,
            segments=tuple(w.name for w in self.writers[:n_inputs]) + ((log.name,) if log is not None else ()))
        wiring = TaskWiring(plan, np.zeros(max(n_inputs, 1)), np.zeros(0), status)
        os.environ[hotpath.PURE_PYTHON_ENV] = "1" if kind == "python" else "0"
        work = hotpath.cycle_work(TickInfo(), wiring, WordBlock(control, 0, CONTROL_WORDS), status, timing, P,
                                  catch_up=True)
        return work, (Int64Ring(log) if log is not None else None), timing

    def close(self) -> None:
        for segment in self.made:
            segment.unlink()


def median_us(call: Any, repeats: int, rings: list[Int64Ring | None]) -> float:
    """µs per call, each batch started with ``rings`` drained (the calls fill them)."""

    def drain() -> None:
        for ring in rings:
            if ring is not None:
                ring.drain()

    return median_us_per_call(call, repeats, before_batch=drain)


def snapshot_costs(args: argparse.Namespace) -> dict[str, float]:
    """µs per ``snapshot.take`` (median of 200) after one step of each JIWY model."""
    import shutil
    import tempfile

    from rtloop.models import ModelRunnable
    from rtloop.runtime.snapshot import take

    jiwy = Path(__file__).resolve().parent.parent / "examples" / "jiwy"
    sys.path.insert(0, str(jiwy))
    from jiwy_models import JiwyController

    makers: dict[str, Any] = {"JIWY controller (Python model)": JiwyController}
    folder = tempfile.mkdtemp(prefix="bench-readlog-")
    if shutil.which("gcc"):
        from rtloop.models.fmu import FmuModel
        from rtloop.models.fmu_build import build_fmu

        fmu = build_fmu(jiwy / "models" / "fmu", Path(folder) / "JiwyPlant.fmu")
        makers["JIWY plant (FMU, FMI serialize)"] = lambda: ModelRunnable(FmuModel(fmu))
    if shutil.which("g++") and shutil.which("gcc"):
        from rtloop.models.twentysim import TwentySimModel

        for model, label in (("Plant", "JIWY plant (20-sim C++, state arrays)"),
                             ("PlantC", "JIWY plant (20-sim ANSI-C, globals)")):
            makers[label] = lambda model=model: ModelRunnable(
                TwentySimModel(jiwy / "models" / model, cache_dir=Path(folder) / "cache"))
    costs = {}
    try:
        for label, make in makers.items():
            runnable = make()
            runnable.check_period(1_000_000)  # the models are made for 1 ms
            runnable.prerun()
            runnable.tick = TickInfo(cycle=0, period_ns=1_000_000)
            u, y = np.zeros(runnable.n_inputs), np.zeros(runnable.n_outputs)
            runnable.step(u, y)
            samples = []
            for _ in range(200):
                started = time.perf_counter_ns()
                take("bench", runnable, 0, 1, 0, u, y)
                samples.append(time.perf_counter_ns() - started)
            costs[f"snapshot.take: {label}"] = float(np.median(samples)) / 1000
            runnable.postrun()
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return costs


def measure(args: argparse.Namespace) -> dict[str, Any]:
    os.sched_setaffinity(0, {args.cpu})
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
        scheduling = f"SCHED_FIFO {args.priority}"
    except PermissionError:
        scheduling = "SCHED_OTHER (no privileges)"
    kinds = ["rtloop python"] + (["rtloop C"] if hotpath.c_built() else [])
    rig = Rig(4)
    results: dict[str, dict[str, float]] = {}
    try:
        for kind in kinds:
            short = "python" if kind == "rtloop python" else "c"
            row: dict[str, float] = {}
            for n in (1, 4):
                for with_log in (False, True):
                    work, log, _timing = rig.task(short, n, with_log)
                    work.start(0, 2**62, 0)
                    label = "read log" if with_log else "no read log (before)"
                    row[f"{n} conn, clean, {label}"] = median_us(lambda w=work: w.read_inputs(P), args.repeats, [log])
                    row[f"{n} conn, stale, {label}"] = median_us(lambda w=work: w.read_inputs(2 * P), args.repeats,
                                                                 [log])
                    work.close()
            step = NoOp().step
            u = y = np.zeros(0)
            for with_log in (False, True):
                work, log, timing = rig.task(short, 1, with_log)
                work.start(rt.now_ns() - 10_000_000_000, 2**62, 0)

                def iterate(w=work, step=step, u=u, y=y) -> None:
                    w.begin()
                    step(u, y)
                    w.finish()

                label = "read log" if with_log else "no read log (before)"
                row[f"no-op iteration, 1 conn, {label}"] = median_us(iterate, min(args.repeats, 5000), [log, timing])
                work.close()
            results[kind] = row
        results["snapshot"] = snapshot_costs(args)
    finally:
        rig.close()
        os.environ.pop(hotpath.PURE_PYTHON_ENV, None)
    return {"machine": machine_facts(), "scheduling": scheduling, "cpu": args.cpu, "repeats": args.repeats,
            "costs_us": results}


def report_markdown(result: dict[str, Any]) -> str:
    costs = dict(result["costs_us"])
    snapshot = costs.pop("snapshot", {})
    kinds = list(costs)
    cases = list(next(iter(costs.values())))
    rows = [[case, *(f"{costs[kind][case]:.3f}" for kind in kinds)] for case in cases]
    title = (f"#### Read log: µs per call, medians of 11 × {result['repeats']} calls, CPU {result['cpu']}, "
             f"{result['scheduling']}")
    snapshots = markdown_table(["snapshot", "µs (median of 200)"], [[k, f"{v:.1f}"] for k, v in snapshot.items()])
    return "\n".join([title, "", markdown_table(["case", *kinds], rows), "", snapshots, "",
                      facts_markdown(result["machine"])])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=4000, help="calls per batch (at most 65536)")
    parser.add_argument("--cpu", type=int, default=max(os.sched_getaffinity(0)))
    parser.add_argument("--priority", type=int, default=80)
    add_output_options(parser)
    args = parser.parse_args(argv)
    if not 0 < args.repeats <= RING:
        parser.error(f"--repeats must be 1..{RING}")
    result = measure(args)
    return print_and_save(report_markdown(result), result, args.json)


if __name__ == "__main__":
    sys.exit(main())
