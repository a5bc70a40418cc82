"""rtloop's hop next to the peers a Python user could pick, in one run: iceoryx2 and dora-rs.

One-way hop latency, writer on one CPU, reader on another, both SCHED_FIFO, a sample every
period: the writer sleeps to just before its send time and spins to it, stamps the sample
with CLOCK_MONOTONIC and sends; the reader busy-polls and takes ``now − stamp``. Blocks of
``raw numpy``, ``rtloop python``, ``rtloop C`` (benchmarks/bench_hotpath.py) and
``iceoryx2`` (publisher → subscriber, a ctypes payload of one int64 stamp and two doubles,
``loan_uninit``/``write_payload``/``send`` and ``receive``) alternate, round after round.
Then, in the same run, ``dora-rs`` Python nodes (``dora run``, no coordinator, the daemon
and both nodes under ``chrt -f PRIORITY``, sender and receiver pinned like the others): a
1 ms dora timer → sender node → receiver node; the sender stamps each tick's sample, the
receiver takes ``now − stamp`` and the arrival times (period jitter = arrival_k −
arrival_k−1 − P). Nodes: ``benchmarks/peers/dora_*.py``.

Usage (as root, ``pip install iceoryx2 dora-rs dora-rs-cli``)::

    python benchmarks/bench_peers.py --rounds 4 --block-s 5
"""

from __future__ import annotations

import argparse
import ctypes
import multiprocessing
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import PmQos, markdown_table, stats_us
from bench_channels import _realtime
from bench_hotpath import collect_hops

from rtloop.linux import rt


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


PEERS = Path(__file__).resolve().parent / "peers"


def run_dora(args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray]:
    """(hops, period jitter) in ns of one dora-rs block, or empty arrays with the reason printed."""
    cycles = max(1, round(args.block_s * 1e6 / args.hop_period_us))
    if args.hop_period_us % 1000:
        raise SystemExit("dora's timer ticks in whole milliseconds: use --hop-period-us 1000, 2000, ...")
    work = Path(tempfile.mkdtemp(prefix="bench-peers-dora-"))
    try:
        (work / "dataflow.yml").write_text(
            "nodes:\n"
            f"  - id: sender\n    path: {PEERS / 'dora_sender.py'}\n"
            f"    args: {cycles} {args.writer_cpu} {work / 'ticks.npy'}\n"
            f"    inputs:\n      tick: dora/timer/millis/{args.hop_period_us // 1000}\n    outputs:\n      - stamp\n"
            f"  - id: receiver\n    path: {PEERS / 'dora_receiver.py'}\n"
            f"    args: {cycles} {args.reader_cpu} {work / 'hops.npz'}\n"
            "    inputs:\n      stamp: sender/stamp\n"
        )
        dora = shutil.which("dora", path=os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]]))
        if dora is None:
            raise SystemExit("dora-rs-cli is not installed (pip install dora-rs dora-rs-cli)")
        env = {**os.environ, "PATH": os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]])}
        subprocess.run(["chrt", "-f", str(args.priority), dora, "run", str(work / "dataflow.yml")], cwd=work,
                       env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                       timeout=args.block_s + 60)
        with np.load(work / "hops.npz") as data:
            hops, arrivals = data["hops"], data["arrivals"]
        return hops, np.diff(arrivals) - args.hop_period_us * 1000
    finally:
        shutil.rmtree(work, ignore_errors=True)


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
    jitter: list[np.ndarray] = []
    with PmQos(True):
        for block in range(args.rounds):
            one_round = argparse.Namespace(**{**vars(args), "rounds": 1})
            for kind, result in collect_hops(one_round).items():
                hops.setdefault(kind, []).append(result)
            hops.setdefault("iceoryx2", []).append(run_iceoryx2(args, block))
            dora_hops, dora_jitter = run_dora(args)
            hops.setdefault("dora-rs", []).append(dora_hops)
            jitter.append(dora_jitter)
    rows = []
    for kind, blocks in hops.items():
        everything = np.concatenate(blocks)
        stats = stats_us(everything)
        rows.append([kind, str(everything.size), stats["p50"], stats["p99"], stats["max"]])
    print(f"One-way hop, {args.rounds} rounds × {args.block_s:g} s blocks per contender, "
          f"a sample every {args.hop_period_us} µs, writer CPU {args.writer_cpu} → reader CPU {args.reader_cpu}\n")
    print(markdown_table(["contender", "samples", "hop p50 µs", "p99 µs", "max µs"], rows))
    period_jitter = stats_us(np.abs(np.concatenate(jitter)))
    print(f"\ndora-rs period jitter at the receiver, |arrival_k − arrival_k−1 − P|: p50 {period_jitter['p50']:.1f} µs, "
          f"p99 {period_jitter['p99']:.1f} µs, max {period_jitter['max']:.1f} µs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
