"""The per-cycle hot path, compiled (C) vs its Python twin vs raw numpy shared memory, in one run.

1. One-way hop latency, writer on one CPU, reader on another, both SCHED_FIFO (the method
   of bench_channels.py): ``raw numpy`` (two values and a counter, no seqlock), ``rtloop
   python`` and ``rtloop C`` (a task's ``publish_outputs`` → a task's ``read_inputs``, the
   whole wiring path). Blocks alternate in one run.
2. Per-cycle cost of 0, 1, 4, 16 input connections (each from its own writer, plus 4 from
   one writer): median cost of ``read_inputs`` in one process pinned to a CPU.
3. The whole no-op iteration ``begin(); step(u, y); finish()`` with releases in the past
   (so ``clock_nanosleep`` returns at once); "sleep excluded" subtracts that call's cost.
   Measured directly too: the C core sums the time from each wake-up to the next sleep
   (``Core.measure_busy()``, ``Core.busy``), with releases in the past and at 10 kHz.
4. A per-operation table; 5. threads and VmLck of a running task process.

Usage (as root)::

    python benchmarks/bench_hotpath.py --quick
    python benchmarks/bench_hotpath.py --rounds 4 --block-s 10 --json hotpath.json
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (
    NoOp,
    PmQos,
    add_output_options,
    closing_sections,
    machine_facts,
    markdown_table,
    median_us_per_call,
    parse_options,
    print_and_save,
    result_head,
    stats_us,
)
from bench_channels import READER_READY, WRITER_READY, _realtime, _wait_for_t0, decode, encode, run_hop_processes

from rtloop.ipc import hotpath
from rtloop.ipc.channels import LetChannel
from rtloop.ipc.ring import Int64Ring
from rtloop.ipc.schema import task_segment_size
from rtloop.ipc.segments import Segment, new_run_token
from rtloop.ipc.status import CONTROL_WORDS, STATUS_WORDS, WordBlock
from rtloop.ipc.wiring import InputLink, TaskWiring, TaskWiringPlan
from rtloop.linux import rt
from rtloop.runnable import TickInfo

KINDS = ("raw numpy", "rtloop python", "rtloop C")
NEWEST = 2**61
CHANNEL_OF = {"rtloop python": 0, "rtloop C": 1}  # each its own writer channel


class Rig:
    """Shared memory for one benchmark: writer channels, a control block, task status/timing blocks."""

    def __init__(self, n_writers: int, n_values: int = 2) -> None:
        self.token, self.owner = new_run_token(), os.getpid()
        self.segments: list[Segment] = []
        self.channels = [self._make(f"w{i}.y", LetChannel.size_bytes(n_values, 8)) for i in range(n_writers)]
        for channel in self.channels:
            LetChannel.initialise(channel, n_values, 8)
        self.raw = self._make("raw", 3 * 8)
        self.control = self._make("control", CONTROL_WORDS * 8)
        self.n_values = n_values

    def _make(self, what: str, size: int) -> Segment:
        segment = Segment.create("bench_hotpath", self.owner, self.token, what, size)
        self.segments.append(segment)
        return segment

    def names(self) -> dict[str, Any]:
        return {"channels": [c.name for c in self.channels], "raw": self.raw.name, "control": self.control.name,
                "n_values": self.n_values}

    def close(self) -> None:
        for segment in self.segments:
            segment.unlink()


def task_io(names: dict[str, Any], kind: str, *, inputs: list[tuple[int, slice, slice]], output: int | None,
            n_inputs: int, n_outputs: int, period_ns: int = 1000) -> tuple[Any, TaskWiring, list[Segment]]:
    """The cycle work of a task reading ``inputs`` (writer, source, target) and publishing to ``output``."""
    os.environ.pop(hotpath.PURE_PYTHON_ENV, None)
    if kind == "rtloop python":
        os.environ[hotpath.PURE_PYTHON_ENV] = "1"
    task = Segment.create("bench_hotpath", os.getpid(), new_run_token(), "task", task_segment_size(1 << 16))
    status = WordBlock(task, 0, STATUS_WORDS)
    timing = Int64Ring.initialise(task, 1 << 16, 4, STATUS_WORDS * 8)
    channels = names["channels"]
    plan = TaskWiringPlan(
        output_channel=channels[output] if output is not None else None,
        inputs=tuple(InputLink(channels[w], source, target, period_ns) for w, source, target in inputs),
        segments=tuple(sorted({channels[w] for w, _, _ in inputs} | ({channels[output]} if output is not None
                                                                       else set()))),
    )
    wiring = TaskWiring(plan, np.zeros(n_inputs), np.zeros(n_outputs), status)
    control = WordBlock(Segment.attach(names["control"]), 0, CONTROL_WORDS)
    io = hotpath.cycle_work(TickInfo(), wiring, control, status, timing, period_ns, True)
    return io, wiring, [task]


# --- 1. hop latency ---------------------------------------------------------------------------------


def hop_writer(names: dict[str, Any], plan: list[str], block_cycles: int, period_ns: int, offset_ns: int,
               spin_ns: int, cpu: int, priority: int) -> None:
    _realtime(cpu, priority, period_ns)
    ios = {kind: task_io(names, kind, inputs=[], output=CHANNEL_OF[kind], n_inputs=0, n_outputs=2)
           for kind in CHANNEL_OF}
    raw = Segment.attach(names["raw"]).array(np.float64, 3)
    control = Segment.attach(names["control"]).buffer.cast("q")
    sleeper, now = rt.AbsoluteSleeper(), rt.now_ns
    t0 = _wait_for_t0(control, WRITER_READY)
    for k in range(len(plan) * block_cycles):
        kind = plan[k // block_cycles]
        send_at = t0 + k * period_ns + offset_ns
        sleeper.sleep_until(send_at - spin_ns)
        while (sent := now()) < send_at:
            pass
        if kind == "raw numpy":
            raw[1] = sent >> 32
            raw[2] = sent & 0xFFFFFFFF
            raw[0] = k + 1
        else:
            io, wiring, _ = ios[kind]
            encode(sent, wiring.y)
            io.publish_outputs(k, sent)


def hop_reader(names: dict[str, Any], plan: list[str], block_cycles: int, period_ns: int, cpu: int, priority: int,
               pipe: Any) -> None:
    _realtime(cpu, priority, period_ns)
    ios = {kind: task_io(names, kind, inputs=[(CHANNEL_OF[kind], slice(0, 2), slice(0, 2))], output=None,
                         n_inputs=2, n_outputs=0)
           for kind in CHANNEL_OF}
    for io, _, _ in ios.values():
        io.start(0, 2**62, 0)
    raw = Segment.attach(names["raw"]).array(np.float64, 3)
    published = {kind: LetChannel(Segment.attach(names["channels"][i])).words for kind, i in CHANNEL_OF.items()}
    control = Segment.attach(names["control"]).buffer.cast("q")
    sleeper, now = rt.AbsoluteSleeper(), rt.now_ns
    out = np.zeros(2)
    hops: dict[str, list[int]] = {kind: [] for kind in KINDS}
    t0 = _wait_for_t0(control, READER_READY)
    seen_let = {kind: words[0] for kind, words in published.items()}
    seen_raw = raw[0]
    for k in range(len(plan) * block_cycles):
        kind = plan[k // block_cycles]
        release = t0 + k * period_ns
        give_up = release + period_ns * 9 // 10
        sleeper.sleep_until(release)
        received = 0
        if kind == "raw numpy":
            while raw[0] == seen_raw and (received := now()) < give_up:
                pass
            if received < give_up:
                seen_raw = raw[0]
                out[:] = raw[1:3]
                received = now()
        else:
            io, wiring, _ = ios[kind]
            words = published[kind]
            while words[0] == seen_let[kind] and (received := now()) < give_up:
                pass
            if received < give_up:
                seen_let[kind] = words[0]
                io.read_inputs(NEWEST)
                received = now()
                out[:] = wiring.u
        if received < give_up and decode(out) >= release:
            hops[kind].append(received - decode(out))
    pipe.send({kind: np.array(v, dtype=np.int64) for kind, v in hops.items()})


def run_hops(args: argparse.Namespace) -> dict[str, Any]:
    hops = collect_hops(args)
    return {kind: {"samples": int(hops[kind].size), "hop_us": stats_us(hops[kind])} for kind in KINDS}


def collect_hops(args: argparse.Namespace) -> dict[str, np.ndarray]:
    """One-way hops in ns per kind, blocks alternating over ``args.rounds`` rounds."""
    period_ns = args.hop_period_us * 1000
    block_cycles = max(1, round(args.block_s * 1e9 / period_ns))
    plan = [KINDS[(i + r) % 3] for r in range(args.rounds) for i in range(3)]
    rig = Rig(2)
    try:
        return run_hop_processes(
            (hop_reader, (rig.names(), plan, block_cycles, period_ns, args.reader_cpu, args.priority)),
            (hop_writer, (rig.names(), plan, block_cycles, period_ns, 200_000, 50_000, args.writer_cpu,
                          args.priority)),
            rig.control, len(plan) * block_cycles * period_ns / 1e9)
    finally:
        rig.close()


# --- 2.–4. costs in one process ----------------------------------------------------------------------


def busy_us(cycle: Any, step: Any, period_ns: int, first_release_ns: int, iterations: int,
            blocks: int) -> float:
    """Mean time from a wake-up to the next sleep, measured by the C core itself, over the
    task's own loop (``while begin(): step(u, y); finish()``, as ``run_loop``); the least of
    ``blocks`` block means, so that a block a neighbour preempted does not count."""
    u = y = np.zeros(0)
    means = []
    for block in range(blocks):
        t0_ns = first_release_ns(block)
        cycle.start(t0_ns, t0_ns + iterations * period_ns, 0)
        cycle.measure_busy()
        while cycle.begin():
            step(u, y)
            cycle.finish()
        total_ns, count, _ = cycle.busy
        means.append(total_ns / max(count, 1) / 1000)
    return min(means)


def measure_costs(args: argparse.Namespace) -> dict[str, Any]:
    previous = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {args.reader_cpu})
    # SCHED_FIFO, so that a clock_nanosleep that returns at once is not a chance for others to run
    previous_policy, previous_param = os.sched_getscheduler(0), os.sched_getparam(0)
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.priority))
    rig = Rig(16)
    made: list[Segment] = []
    try:
        names = rig.names()
        for i in range(16):  # every writer has published once, at t = 0
            LetChannel(rig.channels[i]).publish(0, np.array([1.0, 2.0]))
        connections: dict[str, dict[str, float]] = {}
        operations: dict[str, dict[str, float]] = {}
        iteration: dict[str, dict[str, float]] = {}
        for kind in ("rtloop python", "rtloop C"):
            costs = {}
            cases = {f"{n} connections": [(i, slice(0, 1), slice(i, i + 1)) for i in range(n)] for n in (0, 1, 4, 16)}
            cases["4 connections, one writer"] = [(0, slice(i % 2, i % 2 + 1), slice(i, i + 1)) for i in range(4)]
            for case, inputs in cases.items():
                io, _, segments = task_io(names, kind, inputs=inputs, output=None, n_inputs=16, n_outputs=0)
                made += segments
                io.start(0, 2**62, 0)
                costs[case] = median_us_per_call(lambda io=io: io.read_inputs(1000), args.op_repeats)
            connections[kind] = costs

            writer, _, segments = task_io(names, kind, inputs=[], output=15, n_inputs=0, n_outputs=2)
            made += segments
            reader, _, segments = task_io(names, kind, inputs=[(15, slice(0, 2), slice(0, 2))], output=None,
                                          n_inputs=2, n_outputs=0)
            made += segments
            reader.start(0, 2**62, 0)
            noop, _, segments = task_io(names, kind, inputs=[], output=None, n_inputs=0, n_outputs=0)
            made += segments
            step = NoOp().step
            u = y = np.zeros(0)

            def iterate(noop=noop, step=step, u=u, y=y) -> None:
                noop.begin()
                step(u, y)
                noop.finish()

            # releases 10 s in the past, catch-up policy: clock_nanosleep returns at once every cycle
            noop.start(rt.now_ns() - 10_000_000_000, 2**62, 0)
            sleeper = rt.AbsoluteSleeper()
            past = rt.now_ns() - 1_000_000_000
            sleep_until = hotpath._hotpath.sleep_until if kind == "rtloop C" else sleeper.sleep_until

            def sleep_once(sleep_until=sleep_until, past=past) -> None:
                sleep_until(past)

            whole = median_us_per_call(iterate, min(args.op_repeats, 5000))
            sleep_us = median_us_per_call(sleep_once, args.op_repeats)
            iteration[kind] = {"whole iteration (sleep returns at once)": whole,
                               "clock_nanosleep, deadline past": sleep_us,
                               "iteration, sleep excluded": whole - sleep_us}
            if kind == "rtloop C":
                iteration[kind]["iteration, wake-up → next sleep, measured in C (releases past)"] = busy_us(
                    noop, step, 1000, lambda _: rt.now_ns() - 10_000_000_000, 5000, 20)
                # 10 kHz with real sleeps: caches and branch predictors cool down while the loop sleeps
                paced, _, segments = task_io(names, kind, inputs=[], output=None, n_inputs=0, n_outputs=0,
                                             period_ns=100_000)
                made += segments
                iteration[kind]["iteration, wake-up → next sleep, measured in C (10 kHz, real sleeps)"] = busy_us(
                    paced, step, 100_000, lambda _: rt.now_ns() + 1_000_000, 2000, 10)
            operations[kind] = {
                "read_inputs, 1 connection (2 values)": connections[kind]["1 connections"],
                "publish_outputs, 1 channel (2 values)": median_us_per_call(
                    lambda writer=writer: writer.publish_outputs(1, 1), args.op_repeats),
                "read_inputs, 0 connections (call overhead)": connections[kind]["0 connections"],
            }
        raw = rig.raw.array(np.float64, 3)
        out = np.zeros(2)

        def raw_write() -> None:
            raw[1] = 1.0
            raw[2] = 2.0
            raw[0] = 1.0

        def raw_read() -> None:
            out[:] = raw[1:3]

        operations["raw numpy"] = {"write 2 values + counter": median_us_per_call(raw_write, args.op_repeats),
                                   "read 2 values": median_us_per_call(raw_read, args.op_repeats),
                                   "rt.now_ns()": median_us_per_call(rt.now_ns, args.op_repeats)}
        return {"connections_us": connections, "iteration_us": iteration, "operations_us": operations}
    finally:
        os.environ.pop(hotpath.PURE_PYTHON_ENV, None)
        os.sched_setscheduler(0, previous_policy, previous_param)
        os.sched_setaffinity(0, previous)
        for segment in made:
            segment.unlink()
        rig.close()


# --- 5. a task process from outside --------------------------------------------------------------------


def task_process_facts(work: Path) -> dict[str, Any]:
    from rtloop.ipc.ports import connect_app
    from rtloop.linux.memory import locked_bytes

    name = f"bench_lean_{os.getpid()}"
    app_file = work / "lean.toml"
    app_file.write_text(f'name = "{name}"\n[tasks.t]\nrunnable = "_common:NoOp"\nperiod_ns = 1_000_000\n')
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), *sys.path])}
    process = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", "2",
                                "--out", str(work / "out")], env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    try:
        app = connect_app(name, timeout_s=20)
        while not (pid := app.task_pids()["t"]):
            time.sleep(0.05)
        time.sleep(0.5)
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
        status = {k: v.strip() for k, _, v in (line.partition(":") for line in lines)}
        rollup = Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()
        locked_resident = next(line.split()[1] for line in rollup if line.startswith("Locked:"))
        locked = locked_bytes(pid) or 0
    finally:
        if process.poll() is None:  # measured (or given up): Ctrl-C ends the run, its duration is only a bound
            process.send_signal(signal.SIGINT)
        process.communicate(timeout=30)
    return {"threads": int(status["Threads"]), "VmLck_MB": int(status["VmLck"].split()[0]) / 1024,
            "locked_proportional_MB": int(locked_resident) / 1024, "locked_MB": locked / 2**20,
            "VmRSS_MB": int(status["VmRSS"].split()[0]) / 1024}


def run(args: argparse.Namespace) -> dict[str, Any]:
    facts = machine_facts()
    started = time.monotonic()
    with PmQos(not args.no_pm_qos) as qos, tempfile.TemporaryDirectory(prefix="rtloop-bench-hotpath-") as work:
        facts["cpu_dma_latency_held_at_0us"] = qos.active
        hops = run_hops(args)
        costs = measure_costs(args)
        lean = task_process_facts(Path(work))
    raw_p50 = hops["raw numpy"]["hop_us"]["p50"]
    c_p50 = hops["rtloop C"]["hop_us"]["p50"]
    conn = costs["connections_us"]["rtloop C"]
    four = conn["4 connections"] - conn["0 connections"]
    noop = costs["iteration_us"]["rtloop C"]["iteration, wake-up → next sleep, measured in C (releases past)"]
    return {
        **result_head("hotpath", args, facts, started),
        "hops": hops,
        **costs,
        "task_process": lean,
        "targets": [
            {"target": "hop p50 ≤ 1.3 × raw numpy", "measured": f"{c_p50:.2f} µs vs {raw_p50:.2f} µs "
             f"({c_p50 / raw_p50:.2f}×)", "met": bool(c_p50 <= 1.3 * raw_p50)},
            {"target": "4 input connections add ≤ 1.2 µs", "measured": f"{four:.2f} µs", "met": bool(four <= 1.2)},
            {"target": "no-op iteration, sleep excluded, ≤ 0.5 µs", "measured": f"{noop:.2f} µs (wake-up → next sleep)",
             "met": bool(noop <= 0.5)},
            {"target": "memory locked ≤ 60 MB per task process (resident pages of its locked mappings)",
             "measured": f"{lean['locked_MB']:.0f} MB", "met": bool(lean["locked_MB"] <= 60)},
            {"target": "one thread per task process", "measured": str(lean["threads"]), "met": lean["threads"] == 1},
        ],
    }


def report_markdown(result: dict[str, Any]) -> str:
    s = result["settings"]
    hop_rows = [[kind, e["samples"], *(e["hop_us"][c] for c in ("min", "p50", "p99", "p99.9", "max"))]
                for kind, e in result["hops"].items()]
    kinds = list(result["connections_us"])
    cases = list(result["connections_us"][kinds[0]])
    conn_rows = [[case, *(result["connections_us"][k][case] for k in kinds),
                  *(result["connections_us"][k][case] - result["connections_us"][k]["0 connections"] for k in kinds)]
                 for case in cases]
    iteration_rows = list(dict.fromkeys(what for k in kinds for what in result["iteration_us"][k]))
    iter_rows = [[what, *(result["iteration_us"][k].get(what, float("nan")) for k in kinds)] for what in iteration_rows]
    op_rows = [[f"{group}: {name}", value] for group, ops in result["operations_us"].items()
               for name, value in ops.items()]
    lean = result["task_process"]
    return "\n\n".join([
        f"### One-way hop (µs), writer CPU {s['writer_cpu']} → reader CPU {s['reader_cpu']}, SCHED_FIFO "
        f"{s['priority']}, one sample per {s['hop_period_us']} µs, {s['rounds']} rounds × {s['block_s']} s each",
        markdown_table(["transport", "samples", "min", "p50", "p99", "p99.9", "max"], hop_rows),
        "### read_inputs per cycle (µs, median) and what the connections add",
        markdown_table(["inputs", *(f"{k}" for k in kinds), *(f"added, {k}" for k in kinds)], conn_rows),
        "### Whole no-op iteration begin(); step(u, y); finish() (µs, median)",
        markdown_table(["", *kinds], iter_rows),
        "### Per operation (µs, median, includes the Python call)",
        markdown_table(["operation", "µs"], op_rows),
        f"### A task process from outside: {lean['threads']} thread(s), locked {lean['locked_MB']:.0f} MB "
        f"(its proportional share {lean['locked_proportional_MB']:.0f} MB), VmLck {lean['VmLck_MB']:.0f} MB "
        f"(whole mappings, touched or not), RSS {lean['VmRSS_MB']:.0f} MB",
        *closing_sections(result),
    ])


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--block-s", type=float, default=10.0)
    parser.add_argument("--hop-period-us", type=int, default=1000)
    parser.add_argument("--writer-cpu", type=int, default=0)
    parser.add_argument("--reader-cpu", type=int, default=1)
    parser.add_argument("--priority", type=int, default=80)
    parser.add_argument("--op-repeats", type=int, default=20_000)
    parser.add_argument("--no-pm-qos", action="store_true")
    add_output_options(parser, quick_help="2 rounds × 3 s blocks")
    return parse_options(parser, argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not hotpath.c_built():
        raise SystemExit(f"bench_hotpath compares C with Python; {hotpath.why_python()}")
    result = run(args)
    return print_and_save(report_markdown(result), result, args.json)


if __name__ == "__main__":
    raise SystemExit(main())
