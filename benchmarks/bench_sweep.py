"""``rtloop.sweep`` of JIWY: 100 simulations of 5 s, against the sum of their simulated durations.

Side by side in one run: the sweep on every CPU (``rtloop.sweep``), and the reference, the same
simulations one after the other in this process (``rtloop.simulate`` in a loop, on the first
``--reference-points`` points, scaled to all of them).

Usage::

    python benchmarks/bench_sweep.py                     # 100 points of 5 s
    python benchmarks/bench_sweep.py --points 10 --duration 1
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
JIWY = ROOT / "examples" / "jiwy"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=100)
    parser.add_argument("--duration", type=float, default=5.0, help="simulated seconds per point")
    parser.add_argument("--reference-points", type=int, default=5)
    args = parser.parse_args()
    sys.path.insert(0, str(JIWY))
    import rtloop
    from rtloop.app.appfile import load_app
    from rtloop.toolbox.sweep import grid

    gains = grid(f"0.1:1.0:{args.points}")
    feeds = {"setpoint": JIWY / "setpoints" / "step.csv"}
    with tempfile.TemporaryDirectory(prefix="bench_sweep-") as folder:
        started = time.perf_counter()
        for i, gain in enumerate(gains[: args.reference_points]):
            app = load_app(JIWY / "jiwy.toml")
            app.feed("setpoint", feeds["setpoint"])
            app.tasks["controller"].runnable.set_parameters({"kp_pan": gain})
            rtloop.simulate(app, args.duration, Path(folder) / f"ref{i}")
        per_point_s = (time.perf_counter() - started) / args.reference_points
        result = rtloop.sweep(JIWY / "jiwy.toml", {"controller.kp_pan": gains}, duration_s=args.duration,
                              out=Path(folder) / "sweep", feeds=feeds)
        failed = [r for r in result.rows if r["error"]]
    simulated_s = args.points * args.duration
    print(f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at the end")
    print("| what | points × simulated s | wall-clock s | simulated s per wall-clock s |")
    print("|---|---:|---:|---:|")
    print(f"| one after the other (rtloop.simulate in a loop; {args.reference_points} points, scaled) | "
          f"{args.points} × {args.duration:g} | {per_point_s * args.points:.1f} | "
          f"{simulated_s / (per_point_s * args.points):.1f} |")
    print(f"| rtloop.sweep, {result.processes} processes | {args.points} × {args.duration:g} | "
          f"{result.elapsed_s:.1f} | {simulated_s / result.elapsed_s:.1f} |")
    print(f"sum of the simulated durations: {simulated_s:g} s; sweep/sum = {result.elapsed_s / simulated_s:.2f}; "
          f"{len(failed)} points failed")


if __name__ == "__main__":
    main()
