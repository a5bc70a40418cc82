"""ROS 2 over DDS from Python: publisher → subscriber latency and drops, by rate.

A publisher process sends ``sensor_msgs/msg/JointState`` (the bridge's message) at a
fixed rate on ``rt/bench/angles`` (absolute-time pacing with ``time.sleep``;
``--spin-us`` spins for the last microseconds instead, which costs a whole CPU). A
subscriber in a separate process waits on a DDS waitset, takes what has arrived and
stamps it. The header stamp carries the send time (``CLOCK_MONOTONIC``,
shared by both processes), ``position[0]`` a sequence number, so each message gives a
one-way latency and missing numbers are drops.

Rates go up until messages are lost; the highest rate with no drops is reported.

    python benchmarks/bench_ros.py                      # sensor QoS, default rates
    python benchmarks/bench_ros.py --qos reliable --rates 1000,5000 --duration-s 3
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import time

import numpy as np

from rtloop.ros.dds import RosPublisher, RosSubscriber
from rtloop.ros.messages import JointState, joint_state, time_to_ns

TOPIC = "/bench/angles"
NAMES = ["pan", "tilt"]
IDLE_END_S = 1.0


def run_subscriber(domain_id: int, qos: str, depth: int | None, expected: int) -> None:
    """Receive until ``expected`` messages or ``IDLE_END_S`` without any; print JSON."""
    sub = RosSubscriber(TOPIC, JointState, qos=qos, domain_id=domain_id, depth=depth)
    print("READY", flush=True)
    # Both sides must have discovered each other, or the first messages are discarded.
    print("MATCHED" if sub.wait_for_publishers(1, timeout_s=10) else "UNMATCHED", flush=True)
    latencies: list[int] = []
    seqs: list[int] = []
    last_rx = time.monotonic()
    first = True
    while len(seqs) < expected:
        if not sub.wait(0.1):
            if not first and time.monotonic() - last_rx > IDLE_END_S:
                break
            if first and time.monotonic() - last_rx > 10:
                break
            continue
        messages = sub.take(256)
        now_ns = time.monotonic_ns()
        last_rx, first = time.monotonic(), False
        for msg in messages:
            latencies.append(now_ns - time_to_ns(msg.header.stamp))
            seqs.append(int(msg.position[0]))
    sub.close()
    print(json.dumps({"latencies_ns": latencies, "seqs": seqs}), flush=True)


def publish_at_rate(pub: RosPublisher, rate_hz: float, count: int, spin_ns: int) -> float:
    """Send ``count`` messages at ``rate_hz``; return the achieved rate."""
    period_ns = round(1e9 / rate_hz)
    start_ns = time.monotonic_ns() + 10_000_000
    for seq in range(count):
        due_ns = start_ns + seq * period_ns
        ahead_ns = due_ns - time.monotonic_ns()
        if ahead_ns > spin_ns:
            time.sleep((ahead_ns - spin_ns) / 1e9)
        while time.monotonic_ns() < due_ns:
            pass
        pub.publish(joint_state(NAMES, [float(seq), 0.5], time.monotonic_ns()))
    elapsed_ns = time.monotonic_ns() - start_ns
    return count / (elapsed_ns / 1e9)


def measure(rate_hz: float, duration_s: float, qos: str, depth: int | None,
            spin_ns: int) -> dict[str, float]:
    """One rate: start a subscriber process, publish, collect its measurements."""
    domain_id = random.randint(1, 101)
    count = max(1, round(rate_hz * duration_s))
    child = subprocess.Popen(
        [sys.executable, __file__, "--role", "sub", "--domain", str(domain_id),
         "--qos", qos, "--expected", str(count), *(["--depth", str(depth)] if depth else [])],
        stdout=subprocess.PIPE, text=True,
    )
    assert child.stdout is not None
    if child.stdout.readline().strip() != "READY":
        raise RuntimeError("subscriber process did not start")
    with RosPublisher(TOPIC, JointState, qos=qos, domain_id=domain_id, depth=depth) as pub:
        matched = child.stdout.readline().strip() == "MATCHED"
        if not (matched and pub.wait_for_subscribers(1, timeout_s=10)):
            raise RuntimeError("publisher and subscriber did not discover each other")
        time.sleep(0.1)
        achieved = publish_at_rate(pub, rate_hz, count, spin_ns)
        out, _ = child.communicate(timeout=duration_s + 30)
    result = json.loads(out.strip().splitlines()[-1])
    latencies_us = np.asarray(result["latencies_ns"], dtype=np.float64) / 1e3
    received = len(set(result["seqs"]))
    missing = sorted(set(range(count)) - set(result["seqs"]))
    return {
        "first_missing": missing[:3],
        "rate_hz": rate_hz,
        "achieved_hz": achieved,
        "sent": count,
        "received": received,
        "drops": count - received,
        "p50_us": float(np.percentile(latencies_us, 50)) if received else float("nan"),
        "p99_us": float(np.percentile(latencies_us, 99)) if received else float("nan"),
        "max_us": float(latencies_us.max()) if received else float("nan"),
    }


def markdown(rows: list[dict[str, float]], qos: str, depth: int | None) -> str:
    """Format results as a markdown table."""
    lines = [
        f"QoS `{qos}` (depth {depth or 'preset'}), JointState (2 joints), Python {sys.version.split()[0]}, "
        f"{os.cpu_count()} CPUs, `{os.uname().release}`",
        "",
        "| rate (Hz) | achieved (Hz) | sent | received | drops | p50 (µs) | p99 (µs) | max (µs) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['rate_hz']:.0f} | {r['achieved_hz']:.0f} | {r['sent']} | {r['received']} | "
            f"{r['drops']} | {r['p50_us']:.0f} | {r['p99_us']:.0f} | {r['max_us']:.0f} |"
        )
    clean = [r["rate_hz"] for r in rows if r["drops"] == 0]
    lines.append("")
    lines.append(f"Highest rate without drops: {max(clean):.0f} Hz" if clean
                 else "Drops at every rate tried.")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=["main", "sub"], default="main")
    parser.add_argument("--domain", type=int, default=0)
    parser.add_argument("--expected", type=int, default=0)
    parser.add_argument("--qos", choices=["sensor", "reliable"], default="sensor")
    parser.add_argument("--rates", default="1000,2000,3000,5000,10000,20000,50000")
    parser.add_argument("--spin-us", type=int, default=0)
    parser.add_argument("--depth", type=int, default=None, help="history depth override")
    parser.add_argument("--duration-s", type=float, default=2.0)
    args = parser.parse_args()
    if args.role == "sub":
        run_subscriber(args.domain, args.qos, args.depth, args.expected)
        return
    rows = []
    for rate in [float(r) for r in args.rates.split(",")]:
        row = measure(rate, args.duration_s, args.qos, args.depth, args.spin_us * 1000)
        rows.append(row)
        print(f"{rate:.0f} Hz: drops {row['drops']} (first {row['first_missing']}), "
              f"p50 {row['p50_us']:.0f} µs", file=sys.stderr)
        if sum(r["drops"] > 0 for r in rows) >= 2:
            break  # two rates with drops: found where it stops keeping up
    print(markdown(rows, args.qos, args.depth))


if __name__ == "__main__":
    main()
