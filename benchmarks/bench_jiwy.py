"""JIWY closed loop at 1 kHz and 5 kHz on this machine: deadline misses and latency.

    sudo python benchmarks/bench_jiwy.py --duration 20

Runs the JIWY app (controller + plant, both SCHED_FIFO on one core, wired both ways,
a setpoint step) with the Python models and with the 20-sim-shaped C++ models, at
1 kHz and at 5 kHz, alternating in one run. At 5 kHz the models keep their 1 ms step
size (the dynamics are wrong, the timing is what is measured; the StepSizeWarning is
silenced here on purpose).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import rtloop
from rtloop import App
from rtloop.models import load_model
from rtloop.models.base import StepSizeWarning

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "jiwy"))  # the example's models
from jiwy_models import JiwyController, JiwyPlant

JIWY = Path(__file__).resolve().parent.parent / "examples" / "jiwy"


def jiwy_app(kind: str, period_ns: int, cpu: int) -> App:
    if kind == "python":
        controller_model, plant_model = JiwyController(), JiwyPlant()
    else:
        controller_model = load_model("20sim:models/Controller", JIWY)
        plant_model = load_model("20sim:models/Plant", JIWY)
    app = App(f"jiwy_{kind}")
    controller = app.add_task("controller", controller_model, period_ns=period_ns, priority=80, cpu=cpu)
    plant = app.add_task("plant", plant_model, period_ns=period_ns, priority=81, cpu=cpu)
    app.connect(plant.y[0:2], controller.u[0:2])
    app.connect(controller.y[0:2], plant.u[0:2])
    app.port("setpoint", to=controller.u[2:4], feed=JIWY / "setpoints" / "step.csv")
    app.record(plant.y)
    return app


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per block")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--cpu", type=int, default=1)
    args = parser.parse_args()
    warnings.simplefilter("ignore", StepSizeWarning)
    results: dict[tuple[str, int], list] = {}
    work = Path(tempfile.mkdtemp(prefix="bench-jiwy-"))
    try:
        for _ in range(args.rounds):
            for kind in ("python", "20sim"):
                for rate_hz in (1000, 5000):
                    app = jiwy_app(kind, 1_000_000_000 // rate_hz, args.cpu)
                    summary = rtloop.run(app, args.duration, work / f"{kind}-{rate_hz}")
                    results.setdefault((kind, rate_hz), []).append(summary)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"JIWY, controller + plant on CPU {args.cpu}, {args.rounds} × {args.duration:g} s per row\n")
    print("| models | rate | task | cycles | misses | miss rate | latency p50 / p99 / max µs | exec p50 µs |")
    print("|---|---:|---|---:|---:|---:|---|---:|")
    for (kind, rate_hz), summaries in results.items():
        for task in ("controller", "plant"):
            timings = [s.tasks[task].timing for s in summaries]
            cycles = sum(t.cycles for t in timings)
            misses = sum(t.deadline_misses for t in timings)
            mean_p50 = sum(t.latency_ns.p50 for t in timings) / len(timings)
            mean_p99 = sum(t.latency_ns.p99 for t in timings) / len(timings)
            worst = max(t.latency_ns.max for t in timings)
            latency = f"{mean_p50 / 1e3:.1f} / {mean_p99 / 1e3:.1f} / {worst / 1e3:.1f}"
            exec_p50 = sum(t.exec_ns.p50 for t in timings) / len(timings) / 1e3
            print(f"| {kind} | {rate_hz} Hz | {task} | {cycles} | {misses} | {misses / max(cycles, 1):.2%} | "
                  f"{latency} | {exec_p50:.1f} |")
    print("\n(p50/p99: mean over rounds; max: worst round)")


if __name__ == "__main__":
    main()
