"""rtloop's hop next to a peer a Python user could pick, in one run: iceoryx2 (PyPI).

One-way hop latency, writer on one CPU, reader on another, both SCHED_FIFO, a sample every
period: the writer sleeps to just before its send time and spins to it, stamps the sample
with CLOCK_MONOTONIC and sends; the reader busy-polls and takes ``now − stamp``. Blocks of
``raw numpy``, ``rtloop python``, ``rtloop C`` (benchmarks/bench_hotpath.py) and
``iceoryx2`` (publisher → subscriber, a ctypes payload of one int64 stamp and two doubles,
``loan_uninit``/``write_payload``/``send`` and ``receive``) alternate, round after round.

Usage (as root, ``pip install iceoryx2``)::

    python benchmarks/bench_peers.py --rounds 4 --block-s 5
"""

from __future__ import annotations

import argparse
import ctypes
import multiprocessing
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import PmQos, markdown_table, stats_us
from bench_channels import _realtime
from bench_hotpath import collect_hops

from rtloop import rt


class Stamped(ctypes.Structure):
    _fields_ = (("sent_ns", ctypes.c_int64), ("a", ctypes.c_double), ("b", ctypes.c_double))


def _service(name: str) -> tuple[Any, Any]:
    import iceoryx2 as iox2

    node = iox2.NodeBuilder.new().create(iox2.ServiceType.Ipc)
    service = node.service_builder(iox2.ServiceName.new(name)).publish_subscribe(Stamped).open_or_create()
    return node, service


def iceoryx2_publisher(name: str, cycles: int, period_ns: int, cpu: int, priority: int, start: Any) -> None:
    _node, service = _service(name)
    publisher = service.publisher_builder().create()
    _realtime(cpu, priority, period_ns)
    start.wait()
    sleeper, now = rt.AbsoluteSleeper(), rt.now_ns
    t0 = now() + 200_000_000
    for k in range(cycles):
        send_at = t0 + k * period_ns
        sleeper.sleep_until(send_at - 50_000)
        while (sent := now()) < send_at:
            pass
        sample = publisher.loan_uninit()
        sample.write_payload(Stamped(sent, 1.0, 2.0)).send()


def iceoryx2_subscriber(name: str, cycles: int, period_ns: int, cpu: int, priority: int, start: Any,
                        results: Any) -> None:
    _node, service = _service(name)
    subscriber = service.subscriber_builder().create()
    _realtime(cpu, priority, period_ns)
    hops = np.zeros(cycles, dtype=np.int64)
    received = 0
    now = rt.now_ns
    start.wait()
    give_up = now() + 200_000_000 + cycles * period_ns + 2_000_000_000
    while received < cycles and now() < give_up:
        sample = subscriber.receive()
        if sample is None:
            continue
        hops[received] = now() - sample.payload().contents.sent_ns
        received += 1
        del sample
    results.send(hops[:received])


def run_iceoryx2(args: argparse.Namespace, block: int) -> np.ndarray:
    period_ns = args.hop_period_us * 1000
    cycles = max(1, round(args.block_s * 1e9 / period_ns))
    name = f"rtloop_bench_peers_{os.getpid()}_{block}"
    context = multiprocessing.get_context("spawn")
    start = context.Barrier(2)
    receive, send = context.Pipe(duplex=False)
    reader = context.Process(target=iceoryx2_subscriber,
                             args=(name, cycles, period_ns, args.reader_cpu, args.priority, start, send))
    writer = context.Process(target=iceoryx2_publisher,
                             args=(name, cycles, period_ns, args.writer_cpu, args.priority, start))
    reader.start()
    writer.start()
    try:
        if not receive.poll(cycles * period_ns / 1e9 + 30):
            raise SystemExit("the iceoryx2 subscriber did not report")
        return receive.recv()
    finally:
        for process in (writer, reader):
            process.join(10)
            if process.is_alive():
                process.kill()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--block-s", type=float, default=5.0)
    parser.add_argument("--hop-period-us", type=int, default=1000)
    parser.add_argument("--writer-cpu", type=int, default=0)
    parser.add_argument("--reader-cpu", type=int, default=1)
    parser.add_argument("--priority", type=int, default=80)
    args = parser.parse_args(argv)
    hops: dict[str, list[np.ndarray]] = {}
    with PmQos(True):
        for block in range(args.rounds):
            one_round = argparse.Namespace(**{**vars(args), "rounds": 1})
            for kind, result in collect_hops(one_round).items():
                hops.setdefault(kind, []).append(result)
            hops.setdefault("iceoryx2", []).append(run_iceoryx2(args, block))
    rows = []
    for kind, blocks in hops.items():
        everything = np.concatenate(blocks)
        stats = stats_us(everything)
        rows.append([kind, str(everything.size), stats["p50"], stats["p99"], stats["max"]])
    print(f"One-way hop, {args.rounds} rounds × {args.block_s:g} s blocks per contender, "
          f"a sample every {args.hop_period_us} µs, writer CPU {args.writer_cpu} → reader CPU {args.reader_cpu}\n")
    print(markdown_table(["contender", "samples", "hop p50 µs", "p99 µs", "max µs"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
