"""One-way hop latency through rtloop's channels, and the per-cycle cost of connections.

Part 1 — hop latency, writer on one CPU, reader on another, both SCHED_FIFO. Every
period the reader wakes (absolute clock_nanosleep) and spins; a little later the writer
wakes, reads CLOCK_MONOTONIC and publishes that send time; the reader notices the new
sample, reads it, takes its receive time and records receive − send. The time travels
as two float64 values (high and low 32 bits: each exact), so no precision is lost.
Blocks of the three transports alternate in one run:

- ``LetChannel``  ``publish(stamp, values)``; the reader spins on the published count,
                  then ``read_valid_at`` (the seqlock read a task does every cycle).
- ``SampleQueue`` ``push(tick, values)``; the reader spins on ``sent``, then ``drain()``.
- ``raw numpy``   the same two values stored into a plain numpy array over shared memory,
                  then a counter; no seqlock, no fence (the floor any transport can reach).

/dev/cpu_dma_latency is held at 0 µs for the whole run (``--no-pm-qos``: not), as
bench_latency.py does; on the KVM guest measured here it cuts the hop median by 2–15 µs.

Part 2 — per-cycle cost of connections: the ``exec_ns`` (end − start) of a no-op task
with no connections vs the same task reading 4 inputs, each connected from its own
writer task (an App of 5 tasks); blocks alternate in one run.

Usage (as root)::

    python benchmarks/bench_channels.py --quick
    python benchmarks/bench_channels.py --rounds 4 --block-s 15 --json channels.json
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import rtloop

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (
    NoOp,
    PmQos,
    add_output_options,
    closing_sections,
    load_timing_csv,
    machine_facts,
    markdown_table,
    median_us_per_call,
    parse_options,
    print_and_save,
    result_head,
    stats_us,
    trim,
)

from rtloop.app.builder import App
from rtloop.ipc.channels import LetChannel
from rtloop.ipc.ring import SampleQueue
from rtloop.ipc.segments import Segment, new_run_token
from rtloop.linux import rt

TRANSPORTS = ("LetChannel", "SampleQueue", "raw numpy")
LOW_BITS = 1 << 32
NEWEST = 2**62
T0_WORD, WRITER_READY, READER_READY = 0, 1, 2  # words of the control segment
START_MARGIN_NS = 100_000_000  # read_valid_at(NEWEST): the newest complete slot, whatever its stamp


def encode(t_ns: int, out: np.ndarray) -> None:
    """Split a CLOCK_MONOTONIC time into two float64 values, each exactly representable."""
    out[0] = t_ns >> 32
    out[1] = t_ns & (LOW_BITS - 1)


def decode(values: np.ndarray) -> int:
    return (int(values[0]) << 32) | int(values[1])


class Transports:
    """The three transports over shared memory, created by the parent, attached by the children."""

    def __init__(self, names: dict[str, str]) -> None:
        self.segments = {kind: Segment.attach(name) for kind, name in names.items()}
        self.let = LetChannel(self.segments["let"])
        self.queue = SampleQueue(self.segments["queue"])
        self.raw = self.segments["raw"].array(np.float64, 3)
        self.control = self.segments["control"].buffer.cast("q")

    @staticmethod
    def create(n_slots: int, capacity: int) -> tuple[dict[str, str], list[Segment]]:
        token, owner = new_run_token(), os.getpid()  # lets a later run remove them if this one dies
        segments = {
            "let": Segment.create("bench_hop", owner, token, "let", LetChannel.size_bytes(2, n_slots)),
            "queue": Segment.create("bench_hop", owner, token, "queue", SampleQueue.size_bytes(2, capacity)),
            "raw": Segment.create("bench_hop", owner, token, "raw", 3 * 8),
            "control": Segment.create("bench_hop", owner, token, "control", 8 * 8),
        }
        LetChannel.initialise(segments["let"], 2, n_slots)
        SampleQueue.initialise(segments["queue"], 2, capacity)
        return {kind: segment.name for kind, segment in segments.items()}, list(segments.values())


def _realtime(cpu: int, priority: int, period_ns: int) -> None:
    settings = rt.apply_realtime(cpu, "fifo", priority, period_ns)
    if not settings.rt:
        raise SystemExit(f"cpu {cpu}: not real-time: {settings.reasons}")


def _wait_for_t0(control: memoryview, ready_word: int) -> int:
    """Say ready, then wait until the parent has set T0 (control word 0)."""
    control[ready_word] = 1
    while not control[0]:
        time.sleep(0.001)
    return control[0]


def hop_writer(names: dict[str, str], plan: list[str], block_cycles: int, period_ns: int, offset_ns: int,
               spin_ns: int, cpu: int, priority: int) -> None:
    """Writer process: at T0 + k·P + offset, stamp CLOCK_MONOTONIC and publish it.

    It wakes ``spin_ns`` early and busy-waits to the send time, so the send does not
    include the cost of coming back from idle (cold caches, a halted vCPU).
    """
    _realtime(cpu, priority, period_ns)
    shm = Transports(names)
    values = np.zeros(2)
    sleeper, now = rt.AbsoluteSleeper(), rt.now_ns
    t0 = _wait_for_t0(shm.control, WRITER_READY)
    for k in range(len(plan) * block_cycles):
        kind = plan[k // block_cycles]
        send_at = t0 + k * period_ns + offset_ns
        sleeper.sleep_until(send_at - spin_ns)
        while (sent := now()) < send_at:
            pass
        encode(sent, values)
        if kind == "LetChannel":
            shm.let.publish(sent, values)
        elif kind == "SampleQueue":
            shm.queue.push(k, values)
        else:
            raw = shm.raw
            raw[1] = values[0]
            raw[2] = values[1]
            raw[0] = k + 1  # announce after the data; x86 keeps store order, aarch64 would not


def hop_reader(names: dict[str, str], plan: list[str], block_cycles: int, period_ns: int, cpu: int,
               priority: int, pipe: Any) -> None:
    """Reader process: wake at T0 + k·P, spin until the sample of cycle k arrives, record the hop."""
    _realtime(cpu, priority, period_ns)
    shm = Transports(names)
    out = np.zeros(2)
    sources = shm.let.source_views(slice(0, 2))
    sleeper, now = rt.AbsoluteSleeper(), rt.now_ns
    let, queue, raw, let_words = shm.let, shm.queue, shm.raw, shm.let.words
    hops: dict[str, list[int]] = {kind: [] for kind in TRANSPORTS}
    lost = dict.fromkeys(TRANSPORTS, 0)
    t0 = _wait_for_t0(shm.control, READER_READY)
    seen_let, seen_queue, seen_raw = let_words[0], queue.sent, raw[0]
    for k in range(len(plan) * block_cycles):
        kind = plan[k // block_cycles]
        release = t0 + k * period_ns
        give_up = release + period_ns * 9 // 10
        sleeper.sleep_until(release)
        while True:  # until this cycle's sample arrives; a late one from the last cycle is skipped
            received = 0
            if kind == "LetChannel":
                while let_words[0] == seen_let and (received := now()) < give_up:
                    pass
                if received < give_up:
                    seen_let = let_words[0]
                    stamp = let.read_valid_at(NEWEST, sources, out)
                    received = now()
                    if stamp != decode(out):
                        raise SystemExit(f"LetChannel returned stamp {stamp} with values {decode(out)}")
            elif kind == "SampleQueue":
                while queue.sent == seen_queue and (received := now()) < give_up:
                    pass
                if received < give_up:
                    _, rows = queue.drain()
                    received = now()
                    seen_queue = queue.received  # what the drain took: a push between `sent` and it too
                    if not len(rows):
                        continue  # the last drain took this sample already (a slow or preempted reader)
                    out[:] = rows[-1]
            else:
                while raw[0] == seen_raw and (received := now()) < give_up:
                    pass
                if received < give_up:
                    seen_raw = raw[0]
                    out[:] = raw[1:3]
                    received = now()
            if received >= give_up:
                lost[kind] += 1  # the writer was more than 0.9 P late
                break
            if decode(out) >= release:
                hops[kind].append(received - decode(out))
                break
    pipe.send({"hops": {kind: np.array(v, dtype=np.int64) for kind, v in hops.items()}, "lost": lost})


def run_hop_processes(reader: tuple[Callable[..., None], tuple[Any, ...]],
                      writer: tuple[Callable[..., None], tuple[Any, ...]], control_segment: Segment,
                      duration_s: float) -> Any:
    """Start the hop reader (the sending end of a pipe after its arguments) and writer in spawned
    processes, set T0 in ``control_segment`` once both say they are ready, and return what the reader
    sends back; neither process outlives this call."""
    context = multiprocessing.get_context("spawn")
    receive, send = context.Pipe(duplex=False)
    processes = [context.Process(target=reader[0], args=(*reader[1], send)),
                 context.Process(target=writer[0], args=writer[1])]
    try:
        for process in processes:
            process.start()
        control = control_segment.buffer.cast("q")
        while not (control[WRITER_READY] and control[READER_READY]):
            if not all(process.is_alive() for process in processes):
                raise SystemExit("a hop benchmark process died while starting")
            time.sleep(0.005)
        control[T0_WORD] = rt.now_ns() + START_MARGIN_NS
        del control
        if not receive.poll(duration_s + 30):
            raise SystemExit("the hop reader did not report (died or stalled)")
        result = receive.recv()
        for process in processes:
            process.join()
        return result
    finally:
        for process in processes:
            if process.is_alive():
                process.kill()


def run_hops(args: argparse.Namespace) -> dict[str, Any]:
    period_ns = args.hop_period_us * 1000
    block_cycles = max(1, round(args.block_s * 1e9 / period_ns))
    plan = [TRANSPORTS[(i + r) % 3] for r in range(args.rounds) for i in range(3)]
    names, segments = Transports.create(n_slots=4, capacity=4096)
    try:
        result = run_hop_processes(
            (hop_reader, (names, plan, block_cycles, period_ns, args.reader_cpu, args.priority)),
            (hop_writer, (names, plan, block_cycles, period_ns, args.offset_us * 1000, args.writer_spin_us * 1000,
                          args.writer_cpu, args.priority)),
            segments[-1], len(plan) * block_cycles * period_ns / 1e9)
    finally:
        for segment in segments:
            segment.unlink()
    return {
        kind: {
            "samples": int(result["hops"][kind].size),
            "lost": int(result["lost"][kind]),
            "hop_us": stats_us(result["hops"][kind]),
        }
        for kind in TRANSPORTS
    }


def measure_operations(repeats: int, cpu: int) -> dict[str, float]:
    """Median cost (µs) of each channel operation, in this process on ``cpu``: where a hop's time goes."""
    from rtloop.ipc.segments import fence

    names, segments = Transports.create(n_slots=4, capacity=4096)
    previous = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(0, {cpu})
        shm = Transports(names)
        let, queue, raw, now = shm.let, shm.queue, shm.raw, rt.now_ns
        values, out = np.zeros(2), np.zeros(2)
        sources = let.source_views(slice(0, 2))

        def queue_round_trip() -> None:
            queue.push(0, values)
            queue.drain()

        def raw_write() -> None:
            raw[1] = values[0]
            raw[2] = values[1]
            raw[0] = 1.0

        def raw_read() -> None:
            out[:] = raw[1:3]

        operations = {
            "fence() (ctypes atomic_thread_fence)": fence,
            "rt.now_ns()": now,
            "encode(now_ns(), values)": lambda: encode(now(), values),
            "LetChannel.publish": lambda: let.publish(1, values),
            "LetChannel.read_valid_at": lambda: let.read_valid_at(NEWEST, sources, out),
            "SampleQueue.push + drain": queue_round_trip,
            "raw numpy write (2 values + counter)": raw_write,
            "raw numpy read (2 values)": raw_read,
        }
        return {name: median_us_per_call(operation, repeats, batches=15) for name, operation in operations.items()}
    finally:
        os.sched_setaffinity(0, previous)
        for segment in segments:
            segment.unlink()


def run_connections(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    """exec_ns of a no-op task with 0 vs 4 input connections (plus the writers' exec with 1 output)."""
    period_ns = args.task_period_us * 1000
    exec_ns: dict[str, list[np.ndarray]] = {"0 connections": [], "4 input connections": [], "writer (1 output)": []}
    for round_index in range(args.rounds):
        for connected in ((False, True) if round_index % 2 == 0 else (True, False)):
            app = App("bench_connections")
            sink = app.add_task("sink", NoOp(n_inputs=4 if connected else 0), period_ns=period_ns,
                                priority=args.priority, cpu=args.reader_cpu)
            if connected:
                for i in range(4):
                    writer = app.add_task(f"w{i}", NoOp(n_outputs=1), period_ns=period_ns,
                                          priority=args.priority, cpu=args.writer_cpu)
                    app.connect(writer.y[0], sink.u[i])
            out = work / f"r{round_index}-{'4' if connected else '0'}conn"
            summary = rtloop.run(app, args.block_s, out, trim=args.trim)
            if not all(task.rt for task in summary.tasks.values()):
                raise SystemExit("tasks did not run real-time")
            timing = load_timing_csv(out / "timing.csv")
            for task, records in timing.items():
                core = trim(records, args.trim)
                sink_key = "4 input connections" if connected else "0 connections"
                key = sink_key if task == "sink" else "writer (1 output)"
                exec_ns[key].append(core[:, 3] - core[:, 2])
    return {
        key: {"samples": int(sum(a.size for a in arrays)), "exec_us": stats_us(np.concatenate(arrays))}
        for key, arrays in exec_ns.items()
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    facts = machine_facts()
    work = Path(tempfile.mkdtemp(prefix="rtloop-bench-channels-"))
    started = time.monotonic()
    try:
        with PmQos(not args.no_pm_qos) as qos:
            facts["cpu_dma_latency_held_at_0us"] = qos.active
            hops = run_hops(args)
            operations = measure_operations(args.op_repeats, args.reader_cpu)
            connections = run_connections(args, work)
    finally:
        facts["loadavg_at_end"] = Path("/proc/loadavg").read_text().split()[:3]
        shutil.rmtree(work, ignore_errors=True)
    let_p50 = hops["LetChannel"]["hop_us"]["p50"]
    zero, four = connections["0 connections"]["exec_us"]["p50"], connections["4 input connections"]["exec_us"]["p50"]
    return {
        **result_head("channels", args, facts, started),
        "hops": hops,
        "operations_us": operations,
        "connections": connections,
        "targets": [
            {"target": "LetChannel hop ≤ 1.5 µs median", "measured": f"{let_p50:.2f} µs", "met": bool(let_p50 <= 1.5)},
            {"target": "(information) cost of 4 input connections per cycle, median",
             "measured": f"{four - zero:.2f} µs ({zero:.2f} → {four:.2f} µs)", "met": None},
        ],
    }


def report_markdown(result: dict[str, Any]) -> str:
    settings = result["settings"]
    hop_rows = [[kind, e["samples"], e["lost"], *(e["hop_us"][c] for c in ("min", "p50", "p99", "p99.9", "max"))]
                for kind, e in result["hops"].items()]
    conn_rows = [[key, e["samples"], *(e["exec_us"][c] for c in ("min", "p50", "p99", "p99.9", "max"))]
                 for key, e in result["connections"].items()]
    return "\n\n".join([
        f"### One-way hop latency (µs), writer CPU {settings['writer_cpu']} → reader CPU {settings['reader_cpu']}, "
        f"SCHED_FIFO {settings['priority']}, one sample per {settings['hop_period_us']} µs, "
        f"{settings['rounds']} rounds × {settings['block_s']} s per transport",
        markdown_table(["transport", "samples", "lost", "min", "p50", "p99", "p99.9", "max"], hop_rows),
        "### Where a hop's time goes: median cost of each operation in one process (µs, includes the Python call)",
        markdown_table(["operation", "µs"], list(result["operations_us"].items())),
        f"### Per-cycle cost of connections: exec_ns of a no-op step (µs), period {settings['task_period_us']} µs",
        markdown_table(["task", "samples", "min", "p50", "p99", "p99.9", "max"], conn_rows),
        *closing_sections(result),
    ])


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=4, help="rounds of alternating blocks (default 4)")
    parser.add_argument("--block-s", type=float, default=15.0, help="seconds per block (default 15)")
    parser.add_argument("--hop-period-us", type=int, default=1000, help="one hop sample per period (default 1000)")
    parser.add_argument("--offset-us", type=int, default=200,
                        help="writer publishes this long after the reader woke and started spinning (default 200)")
    parser.add_argument("--writer-spin-us", type=int, default=50,
                        help="writer wakes this early and busy-waits to the send time; 0: send on wake-up (default 50)")
    parser.add_argument("--task-period-us", type=int, default=1000, help="period of the connection-cost apps")
    parser.add_argument("--writer-cpu", type=int, default=0)
    parser.add_argument("--reader-cpu", type=int, default=1)
    parser.add_argument("--priority", type=int, default=80)
    parser.add_argument("--trim", type=int, default=20, help="cycles dropped at each end of every App block")
    parser.add_argument("--op-repeats", type=int, default=20_000, help="calls per timing of each channel operation")
    parser.add_argument("--no-pm-qos", action="store_true", help="do not hold /dev/cpu_dma_latency at 0 µs")
    add_output_options(parser, quick_help="2 rounds × 3 s blocks: under a minute")
    return parse_options(parser, argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    result = run(args)
    return print_and_save(report_markdown(result), result, args.json)


if __name__ == "__main__":
    raise SystemExit(main())
