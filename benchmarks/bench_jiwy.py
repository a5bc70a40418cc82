"""JIWY closed loop at 1 kHz and 5 kHz on this machine: deadline misses and latency.

    sudo python benchmarks/bench_jiwy.py --duration 20
    sudo python benchmarks/bench_jiwy.py --rates 1000,2000,5000,10000 --models python --cyclictest

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

import numpy as np

import rtloop
from rtloop import App
from rtloop.models import load_model
from rtloop.models.base import StepSizeWarning

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "jiwy"))  # the example's models
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import PmQos, load_timing_csv, trim
from bench_latency import Samples, run_cyclictest_block
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


def jiwy_misses(timing_csv: Path, period_ns: int, trim_cycles: int) -> tuple[int, int]:
    """(misses, releases) of the app: a release is missed when any task ends after the next
    release or skips it (the same count as cyclictest's: a wake-up later than one period, or
    a release slept through)."""
    missed: set[int] = set()
    releases = 0
    for records in load_timing_csv(timing_csv).values():
        core = trim(records, trim_cycles)
        if not len(core):
            continue
        cycles, release, _, end = core.T
        releases = max(releases, int(cycles[-1] - cycles[0] + 1))
        missed.update(int(c) for c in cycles[end > release + period_ns])
        gaps = np.flatnonzero(np.diff(cycles) > 1)
        for gap in gaps:
            missed.update(range(int(cycles[gap]) + 1, int(cycles[gap + 1])))
    return len(missed), releases


def cyclictest_misses(cpu: int, period_us: int, duration_s: float, trim_cycles: int) -> tuple[int, int]:
    into = Samples("cyclictest", period_us)
    run_cyclictest_block(argparse.Namespace(priority=80, cpu=cpu, trim=trim_cycles), period_us, duration_s, into)
    latency = into.latency()
    late = int(np.count_nonzero(latency > period_us * 1000))
    return late + into.skipped, len(latency) + into.skipped + into.lost


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per block")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--cpu", type=int, default=1)
    parser.add_argument("--rates", default="1000,5000", help="comma-separated rates in Hz")
    parser.add_argument("--models", default="python,20sim", help="python, 20sim or both")
    parser.add_argument("--cyclictest", action="store_true", help="cyclictest at each rate, same core, same run")
    args = parser.parse_args()
    rates = [int(r) for r in args.rates.split(",")]
    kinds = args.models.split(",")
    warnings.simplefilter("ignore", StepSizeWarning)
    results: dict[tuple[str, int], list] = {}
    misses: dict[tuple[str, int], list[tuple[int, int]]] = {}
    work = Path(tempfile.mkdtemp(prefix="bench-jiwy-"))
    try:
        with PmQos(True):
            for _ in range(args.rounds):
                for rate_hz in rates:
                    period_ns = 1_000_000_000 // rate_hz
                    for kind in kinds:
                        out = work / f"{kind}-{rate_hz}"
                        summary = rtloop.run(jiwy_app(kind, period_ns, args.cpu), args.duration, out)
                        results.setdefault((kind, rate_hz), []).append(summary)
                        misses.setdefault((kind, rate_hz), []).append(jiwy_misses(out / "timing.csv", period_ns, 20))
                    if args.cyclictest:
                        found = cyclictest_misses(args.cpu, period_ns // 1000, args.duration, 20)
                        misses.setdefault(("cyclictest", rate_hz), []).append(found)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"JIWY, controller + plant on CPU {args.cpu}, {args.rounds} × {args.duration:g} s per row\n")
    print("| models | rate | task | cycles | misses | miss rate | latency p50 / p99 / max µs | exec p50 µs |")
    print("|---|---:|---|---:|---:|---:|---|---:|")
    for (kind, rate_hz), summaries in results.items():
        for task in ("controller", "plant"):
            timings = [s.tasks[task].timing for s in summaries]
            cycles = sum(t.cycles for t in timings)
            task_misses = sum(t.deadline_misses for t in timings)
            mean_p50 = sum(t.latency_ns.p50 for t in timings) / len(timings)
            mean_p99 = sum(t.latency_ns.p99 for t in timings) / len(timings)
            worst = max(t.latency_ns.max for t in timings)
            latency = f"{mean_p50 / 1e3:.1f} / {mean_p99 / 1e3:.1f} / {worst / 1e3:.1f}"
            exec_p50 = sum(t.exec_ns.p50 for t in timings) / len(timings) / 1e3
            print(f"| {kind} | {rate_hz} Hz | {task} | {cycles} | {task_misses} | "
                  f"{task_misses / max(cycles, 1):.2%} | {latency} | {exec_p50:.1f} |")
    print("\n(p50/p99: mean over rounds; max: worst round)\n")
    print("Miss rate per release, the app (either task late or skipped) next to cyclictest on the same core:\n")
    print("| rate | " + " | ".join(f"{kind} misses / releases" for kind in [*kinds, "cyclictest"]
                                  if any(k == kind for k, _ in misses)) + " |")
    print("|---:|" + "---:|" * len({k for k, _ in misses}))
    for rate_hz in rates:
        cells = []
        for kind in [*kinds, "cyclictest"]:
            if (kind, rate_hz) not in misses:
                continue
            missed = sum(m for m, _ in misses[(kind, rate_hz)])
            total = sum(n for _, n in misses[(kind, rate_hz)])
            cells.append(f"{missed} / {total} ({missed / max(total, 1):.3%})")
        print(f"| {rate_hz} Hz | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
