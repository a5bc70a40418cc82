"""Per-step cost of each model adapter against calling the same model directly.

    python benchmarks/bench_models.py [--steps 200000] [--repeats 5]

Builds the JIWY fixtures (20-sim-shaped C++ and ANSI-C plant, FMU plant) into a
temporary cache, then times one step of the JIWY plant per way of calling it, in one
process, and prints a markdown table. Each figure is the best of ``--repeats`` runs of
``--steps`` calls (like ``timeit``): the cost when nothing else interferes.
"""

from __future__ import annotations

import argparse
import ctypes
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from rtloop.models import ModelRunnable, load_model
from rtloop.models.fmu_build import build_fmu
from rtloop.models.twentysim import TwentySimModel

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "jiwy"))  # the example's models
from jiwy_models import JiwyController, JiwyPlant

MODELS = Path(__file__).resolve().parents[1] / "examples" / "jiwy" / "models"


def best_ns_per_call(call: Callable[[], object], steps: int, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter_ns()
        for _ in range(steps):
            call()
        best = min(best, (time.perf_counter_ns() - start) / steps)
    return best


def raw_twentysim(model: TwentySimModel, u: np.ndarray, y: np.ndarray) -> dict[str, Callable]:
    """Direct ctypes calls into the shim, as a user would write them by hand."""
    lib = ctypes.CDLL(str(model.library_path))
    lib.rtloop_new.restype = ctypes.c_void_p
    lib.rtloop_initialize.argtypes = [ctypes.c_void_p] * 3 + [ctypes.c_double]
    calc = lib.rtloop_calculate
    calc.argtypes = [ctypes.c_void_p] * 3
    handle = lib.rtloop_new()
    lib.rtloop_initialize(handle, u.ctypes.data, y.ctypes.data, 0.0)
    u_ptr, y_ptr = u.ctypes.data, y.ctypes.data
    return {
        "raw ctypes, pointers cached": lambda: calc(handle, u_ptr, y_ptr),
        "raw ctypes, `.ctypes.data` each call": lambda: calc(handle, u.ctypes.data, y.ctypes.data),
    }


def fmpy_direct(fmu_path: Path, u: np.ndarray, y: np.ndarray) -> tuple[dict[str, Callable], object]:
    """FMPy's convenience wrappers and its checked fmi2* methods with ctypes arrays."""
    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Slave

    md = read_model_description(str(fmu_path))
    fmu = FMU2Slave(
        guid=md.guid,
        modelIdentifier=md.coSimulation.modelIdentifier,
        unzipDirectory=extract(str(fmu_path)),
    )
    fmu.instantiate()
    fmu.setupExperiment(startTime=0.0)
    fmu.enterInitializationMode()
    fmu.exitInitializationMode()
    h = 0.001
    clock = {"t": 0.0}
    vr_in, vr_out = [0, 1], [2, 3]

    def convenience() -> None:
        fmu.setReal(vr_in, u.tolist())
        fmu.doStep(clock["t"], h)
        y[:] = fmu.getReal(vr_out)
        clock["t"] += h

    c_in = (ctypes.c_uint * 2)(*vr_in)
    c_out = (ctypes.c_uint * 2)(*vr_out)
    u_ptr = ctypes.cast(u.ctypes.data, ctypes.POINTER(ctypes.c_double))
    y_ptr = ctypes.cast(y.ctypes.data, ctypes.POINTER(ctypes.c_double))

    def checked_fmi2() -> None:
        fmu.fmi2SetReal(fmu.component, c_in, 2, u_ptr)
        fmu.fmi2DoStep(fmu.component, clock["t"], h, 1)
        fmu.fmi2GetReal(fmu.component, c_out, 2, y_ptr)
        clock["t"] += h

    calls = {
        "FMPy `setReal`/`doStep`/`getReal`": convenience,
        "FMPy `fmi2SetReal`/`fmi2DoStep`/`fmi2GetReal`, ctypes arrays": checked_fmi2,
    }
    return calls, fmu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    rows: list[tuple[str, str, float, float | None]] = []

    def measure(model: str, calls: dict[str, Callable], direct: str) -> None:
        base = best_ns_per_call(calls[direct], args.steps, args.repeats)
        for way, call in calls.items():
            ns = base if way == direct else best_ns_per_call(call, args.steps, args.repeats)
            rows.append((model, way, ns, None if way == direct else ns / base))

    u, y = np.array([0.1, 0.05]), np.zeros(2)
    u4 = np.array([0.01, 0.02, 0.5, 0.3])

    plant = JiwyPlant()
    plant.prerun()
    measure("Python JiwyPlant", {
        "`calculate(u, y)` (direct)": lambda: plant.calculate(u, y),
        "as Runnable: `step(u, y)`": lambda: plant.step(u, y),
    }, "`calculate(u, y)` (direct)")  # fmt: skip
    controller = JiwyController()
    controller.prerun()
    measure("Python JiwyController", {
        "`calculate(u, y)` (direct)": lambda: controller.calculate(u4, y),
        "as Runnable: `step(u, y)`": lambda: controller.step(u4, y),
    }, "`calculate(u, y)` (direct)")  # fmt: skip

    with tempfile.TemporaryDirectory() as tmp:
        for folder, label in (("Plant", "20-sim C++ Plant"), ("PlantC", "20-sim ANSI-C Plant")):
            model = TwentySimModel(MODELS / folder, cache_dir=tmp)
            runnable = ModelRunnable(model)
            runnable.prerun()
            calls = raw_twentysim(model, u.copy(), y.copy())
            calls["ModelRunnable `step(u, y)`"] = lambda r=runnable: r.step(u, y)
            measure(label, calls, "raw ctypes, pointers cached")
            runnable.postrun()

        fmu_path = build_fmu(MODELS / "fmu", Path(tmp) / "JiwyPlant.fmu")
        fmu_runnable = load_model(f"fmu:{fmu_path}")
        fmu_runnable.check_period(1_000_000)  # type: ignore[attr-defined]
        fmu_runnable.prerun()
        calls, fmu = fmpy_direct(fmu_path, u, y.copy())
        calls["ModelRunnable `step(u, y)` (raw calls)"] = lambda: fmu_runnable.step(u, y)
        measure("FMU JiwyPlant (FMI 2.0 CS)", calls, "FMPy `setReal`/`doStep`/`getReal`")
        fmu_runnable.postrun()
        fmu.terminate()  # type: ignore[attr-defined]
        fmu.freeInstance()  # type: ignore[attr-defined]

    print(f"Per-step cost, JIWY plant/controller — {platform.machine()}, "
          f"Python {platform.python_version()}, best of {args.repeats}×{args.steps} steps\n")
    print("| model | way of calling | µs/step | × first row of model |")
    print("|---|---|---:|---:|")
    for model, way, ns, ratio in rows:
        print(f"| {model} | {way} | {ns / 1e3:.3f} | {'1.00' if ratio is None else f'{ratio:.2f}'} |")


if __name__ == "__main__":
    main()
