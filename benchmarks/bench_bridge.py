"""RT task output → ROS 2 subscriber, through the real listener bridge: latency and drops.

An app with one task, ``clock``, whose output is its own tick: ``[cycle, release s,
release ns]`` (the release time on CLOCK_MONOTONIC, split so that it is exact). A
``[[ros.publish]]`` entry sends it every tick as ``sensor_msgs/msg/JointState``; the
bridge stamps each message with the tick's release time on the wall clock. A subscriber
in another process takes what arrives and computes ``receive wall time − header stamp``:
the whole path from the task's release (LET: the value is visible one period later)
through the port queue, the bridge's wake-up on the task's timeline, DDS and the
subscriber's wake-up. Both ends use ROS 2's default QoS (reliable, keep last).

Next to each rate, the same run measures a plain Cyclone DDS publisher → subscriber
(``bench_ros.py``: a Python publisher stamps each message with its send time) at that
rate: the floor the bridge is compared with (target: bridge p50 ≤ 1.5 × plain p50).

Drops are counted at each stage: ticks the task ran (and releases it skipped); ticks the
port queue dropped before the bridge read them; ticks still queued when the bridge was
stopped at the end of the run; messages the bridge published; messages that arrived. The bridge
starts just after the app's epoch and first sends what queued meanwhile, so latencies
are taken over ticks released ``--settle-s`` seconds after T0 or later.

    sudo python benchmarks/bench_bridge.py                       # 1, 2, 5 kHz, 5 s each
    sudo python benchmarks/bench_bridge.py --rates 1000,10000 --duration-s 3
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rtloop import Runnable

NS_PER_S = 1_000_000_000
TOPIC = "/bench/clock"
IDLE_END_S = 1.5

APP = """\
name = "bench_bridge"

[tasks.clock]
runnable = "bench_bridge:ReleaseTime"
period_ns = {period_ns}
priority = 80
cpu = {cpu}

[[ros.publish]]
topic = "{topic}"
source = "clock.y[0:3]"
type = "sensor_msgs/msg/JointState"
joint_names = ["cycle", "release_s", "release_ns"]
every = 1
"""


class ReleaseTime(Runnable):
    """y = [cycle, release time's whole seconds, its nanoseconds] (CLOCK_MONOTONIC), exact in float64."""

    n_inputs, n_outputs = 0, 3

    def step(self, u, y) -> None:
        y[0] = self.tick.cycle
        seconds, nanoseconds = divmod(self.tick.release_ns, NS_PER_S)
        y[1] = seconds
        y[2] = nanoseconds


def run_subscriber(domain_id: int, give_up_s: float) -> None:
    """Take JointStates until ``IDLE_END_S`` without any (or ``give_up_s``); print one JSON line."""
    from rtloop.ros.dds import RosSubscriber
    from rtloop.ros.messages import JointState, time_to_ns

    sub = RosSubscriber(TOPIC, JointState, qos="reliable", domain_id=domain_id, depth=10_000)
    print("READY", flush=True)
    rows: list[tuple[int, int, int]] = []  # (cycle, release_ns, receive wall ns - stamp ns)
    offsets: set[int] = set()  # stamp − release: constant if the stamp is the release time
    start = last = time.monotonic()
    while time.monotonic() - start < give_up_s:
        if not sub.wait(0.1):
            if rows and time.monotonic() - last > IDLE_END_S:
                break
            continue
        messages = sub.take(1024)
        now_ns = time.time_ns()
        last = time.monotonic()
        for msg in messages:
            stamp_ns = time_to_ns(msg.header.stamp)
            cycle, release_s, release_ns = (int(v) for v in msg.position)
            release = release_s * NS_PER_S + release_ns
            rows.append((cycle, release, now_ns - stamp_ns))
            offsets.add(stamp_ns - release)
    sub.close()
    print(json.dumps({"rows": rows, "offsets": sorted(offsets)[:5], "n_offsets": len(offsets)}), flush=True)


def measure(rate_hz: int, duration_s: float, cpu: int, settle_s: float) -> dict[str, float]:
    period_ns = round(NS_PER_S / rate_hz)
    domain_id = random.Random(os.getpid() ^ time.monotonic_ns()).randint(1, 101)
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id),
           "PYTHONPATH": os.pathsep.join(p for p in (str(Path(__file__).parent), os.environ.get("PYTHONPATH")) if p)}
    with tempfile.TemporaryDirectory(prefix="bench_bridge_") as tmp:
        app_file = Path(tmp) / "bench_bridge.toml"
        app_file.write_text(APP.format(period_ns=period_ns, cpu=cpu, topic=TOPIC))
        subscriber = subprocess.Popen(
            [sys.executable, __file__, "--subscriber", str(domain_id), str(duration_s + 30)],
            stdout=subprocess.PIPE, text=True, env=env,
        )
        assert subscriber.stdout is not None
        if subscriber.stdout.readline().strip() != "READY":
            raise SystemExit("subscriber did not start")
        run = subprocess.run(
            [sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration", str(duration_s),
             "--out", str(Path(tmp) / "out"), "--quiet"],
            env=env, capture_output=True, text=True, check=False,
        )
        if run.returncode:
            subscriber.kill()
            raise SystemExit(f"rtloop run failed:\n{run.stderr}")
        report = json.loads(subscriber.communicate(timeout=duration_s + 40)[0])
        summary = json.loads((Path(tmp) / "out" / "summary.json").read_text())
    task = summary["tasks"]["clock"]
    port = summary["ports"]["ros_bench_clock"]
    bridge = summary["bridges"][f"publish {TOPIC}"]
    rows = np.array(report["rows"], dtype=np.int64).reshape(-1, 3)
    t0_ns = rows[:, 1].min() - rows[rows[:, 1].argmin(), 0] * period_ns if len(rows) else 0
    steady = rows[rows[:, 1] >= t0_ns + settle_s * NS_PER_S] if len(rows) else rows
    latency_us = steady[:, 2] / 1e3 if len(steady) else np.array([np.nan])
    return {
        "rate_hz": rate_hz,
        "ticks": task["cycles"],
        "overruns": task["overruns"],
        "deadline_misses": task["deadline_misses"],
        "port_dropped": port["dropped"],
        "unread_at_stop": port["sent"] - port["dropped"] - bridge.get("messages", 0),
        "published": bridge.get("messages", 0),
        "received": len(rows),
        "dds_lost": bridge.get("messages", 0) - len(np.unique(rows[:, 0])),
        "stamp_is_release": report["n_offsets"] == 1,
        "p50_us": float(np.percentile(latency_us, 50)),
        "p99_us": float(np.percentile(latency_us, 99)),
        "max_us": float(latency_us.max()),
        "rt": task["rt"],
        "bridge_state": bridge["state"],
    }


def plain_dds(rate_hz: int, duration_s: float) -> dict[str, float]:
    """A plain Cyclone DDS publisher → subscriber at ``rate_hz`` (bench_ros.py), ROS 2 default QoS."""
    from bench_ros import measure as measure_plain

    result = measure_plain(rate_hz, duration_s, "reliable", None, 0)
    return {"plain_p50_us": result["p50_us"], "plain_p99_us": result["p99_us"], "plain_drops": result["drops"]}


def table(results: list[dict[str, float]]) -> str:
    lines = [
        "| rate | ticks run | skipped (overruns) | port queue dropped | unread at stop | bridge published "
        "| received | lost in DDS "
        "| latency p50 | p99 | max | plain DDS p50 | p99 | bridge p50 / plain p50 |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lines.append(
            f"| {r['rate_hz'] / 1000:g} kHz | {r['ticks']} | {r['overruns']} | {r['port_dropped']} "
            f"| {r['unread_at_stop']} | {r['published']} "
            f"| {r['received']} | {r['dds_lost']} | {r['p50_us'] / 1e3:.2f} ms | {r['p99_us'] / 1e3:.2f} ms "
            f"| {r['max_us'] / 1e3:.2f} ms | {r.get('plain_p50_us', float('nan')) / 1e3:.2f} ms "
            f"| {r.get('plain_p99_us', float('nan')) / 1e3:.2f} ms "
            f"| {r['p50_us'] / r.get('plain_p50_us', float('nan')):.2f} |"
        )
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", default="1000,2000,5000", help="task rates in Hz, comma-separated")
    parser.add_argument("--duration-s", type=float, default=5.0)
    parser.add_argument("--cpu", type=int, default=max(os.sched_getaffinity(0)), help="CPU of the task")
    parser.add_argument("--settle-s", type=float, default=1.0, help="leave out ticks released before T0 + this")
    parser.add_argument("--json", action="store_true", help="print the results as JSON too")
    parser.add_argument("--no-baseline", action="store_true", help="skip the plain DDS pub → sub measurement")
    parser.add_argument("--subscriber", nargs=2, metavar=("DOMAIN", "GIVE_UP_S"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.subscriber:
        run_subscriber(int(args.subscriber[0]), float(args.subscriber[1]))
        return 0
    results = []
    for rate in (int(r) for r in args.rates.split(",")):
        result = measure(rate, args.duration_s, args.cpu, args.settle_s)
        if not args.no_baseline:
            result.update(plain_dds(rate, args.duration_s))
        results.append(result)
        print(f"{rate} Hz: {json.dumps(result)}", file=sys.stderr, flush=True)
    if not all(r["stamp_is_release"] for r in results):
        print("warning: header stamps are not the ticks' release times (offset varies)", file=sys.stderr)
    print(table(results))
    if args.json:
        print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
