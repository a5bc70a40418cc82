"""How long ``rtloop.load`` takes, and how much memory, for long runs at 1 kHz.

A synthetic run directory is written (two 1 kHz tasks, ``--signals`` recorded signals with
full-precision values as the recorder writes them), then loaded in a fresh process each:

- ``rtloop.load``       numpy block parser; above 256 MB a memory-mapped temporary file
- ``csv + lists``       the report's loader before rtloop.load (csv module, a Python list per
                        row), the reference
- ``pandas.read_csv``   signals.csv and timing.csv with pandas' C parser (if pandas is installed)

Both references hold everything in memory, so they run only up to ``--reference-max-hours``.

Peak memory is the process's peak resident set (``ru_maxrss``) minus that of a process that
only imported numpy and rtloop, i.e. what loading added.

Usage::

    python benchmarks/bench_load.py --hours 0.1              # quick
    python benchmarks/bench_load.py --hours 24 --dir /var/tmp  # a day at 1 kHz (≈ 20 GB of CSV)
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PERIOD_NS = 1_000_000
ROWS_PER_WRITE = 100_000

LOADERS = {
    "rtloop.load": """
import rtloop
run = rtloop.load(RUN)
rows = run.signals.rows
cycles = sum(len(t) for t in run.timing.values())
""",
    "csv + lists": """
rows, cycles = legacy_load(RUN)
""",
    "pandas.read_csv": """
import pandas
signals = pandas.read_csv(RUN + "/signals.csv", engine="c")
timing = pandas.read_csv(RUN + "/timing.csv", engine="c")
rows = len(signals)
cycles = len(timing)
""",
}

LEGACY = '''
def legacy_load(path):
    import csv, math
    rows = []
    with open(path + "/signals.csv", newline="") as f:
        r = csv.reader(f); next(r)
        rows = [[float(c) if c else math.nan for c in row] for row in r]
    timing = {}
    with open(path + "/timing.csv", newline="") as f:
        r = csv.reader(f); next(r)
        for row in r:
            timing.setdefault(row[0], []).append([int(c) for c in row[1:5]])
    return len(rows), sum(len(v) for v in timing.values())
'''

MEASURE = """
import resource, sys, time
import numpy, rtloop
RUN = sys.argv[1]
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
started = time.perf_counter()
{code}
elapsed = time.perf_counter() - started
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(elapsed, (peak - base) / 1024, rows, cycles)
"""


def write_run(folder: Path, hours: float, n_signals: int) -> tuple[int, int]:
    """A run directory of ``hours`` at 1 kHz; returns (signal rows, bytes written)."""
    folder.mkdir(parents=True, exist_ok=True)
    cycles = round(hours * 3600 * 1e9 / PERIOD_NS)
    rng = np.random.default_rng(1)
    template = [",".join(repr(float(v)) for v in rng.normal(size=n_signals)) for _ in range(1000)]
    with open(folder / "signals.csv", "w", buffering=1 << 20) as file:
        file.write(",".join(["t_s", *(f"plant.y[{i}]" for i in range(n_signals))]) + "\n")
        for first in range(0, cycles + 1, ROWS_PER_WRITE):
            ks = range(first, min(first + ROWS_PER_WRITE, cycles + 1))
            file.write("".join(f"{k * PERIOD_NS / 1e9!r},{template[k % 1000]}\n" for k in ks))
    t0 = 10**12
    with open(folder / "timing.csv", "w", buffering=1 << 20) as file:
        file.write("task,cycle,release_ns,start_ns,end_ns\n")
        for first in range(0, cycles, ROWS_PER_WRITE):
            for task in ("controller", "plant"):
                ks = range(first, min(first + ROWS_PER_WRITE, cycles))
                file.write("".join(f"{task},{k},{t0 + k * PERIOD_NS},{t0 + k * PERIOD_NS + 20_000 + k % 977},"
                                   f"{t0 + k * PERIOD_NS + 45_000 + k % 1013}\n" for k in ks))
    task = {"period_ns": PERIOD_NS, "cycles": cycles, "trimmed": 40}
    summary = {"app": "bench_load", "mode": "run", "tasks": {"controller": task, "plant": task}, "notes": []}
    (folder / "summary.json").write_text(json.dumps(summary))
    size = sum(p.stat().st_size for p in folder.iterdir())
    return cycles + 1, size


def measure(loader: str, folder: Path) -> dict[str, float]:
    code = LOADERS[loader]
    script = LEGACY + MEASURE.format(code=code)
    result = subprocess.run([sys.executable, "-c", script, str(folder)], capture_output=True, text=True,
                            check=False)
    if result.returncode:
        return {"error": result.stderr.strip().splitlines()[-1] if result.stderr.strip() else "failed"}
    elapsed, peak_mib, rows, cycles = result.stdout.split()
    return {"seconds": float(elapsed), "peak_mib": float(peak_mib), "rows": int(rows), "cycles": int(cycles)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, nargs="+", default=[0.1, 1.0], help="run lengths to load")
    parser.add_argument("--signals", type=int, default=6, help="recorded signals (columns)")
    parser.add_argument("--reference-max-hours", type=float, default=1.0,
                        help="run the references only up to this length (their memory grows with it)")
    parser.add_argument("--dir", type=Path, default=None, help="where to write the synthetic runs")
    args = parser.parse_args()
    try:
        import pandas  # noqa: F401

        have_pandas = True
    except ModuleNotFoundError:
        have_pandas = False
    print(f"python {sys.version.split()[0]}, numpy {np.__version__}; {args.signals} signals, 2 tasks at 1 kHz")
    print("| run length | rows | files | loader | seconds | MB/s | peak memory added [MiB] |")
    print("|---|---:|---:|---|---:|---:|---:|")
    for hours in args.hours:
        folder = Path(tempfile.mkdtemp(prefix="bench_load-", dir=args.dir))
        try:
            started = time.perf_counter()
            rows, size = write_run(folder, hours, args.signals)
            print(f"<!-- wrote {size / 1e9:.2f} GB in {time.perf_counter() - started:.0f} s -->", flush=True)
            loaders = ["rtloop.load"]
            if hours <= args.reference_max_hours:  # both hold everything in memory: a day would not fit
                loaders.append("csv + lists")
                if have_pandas:
                    loaders.append("pandas.read_csv")
            for loader in loaders:
                result = measure(loader, folder)
                if "error" in result:
                    print(f"| {hours:g} h | {rows:,} | {size / 1e9:.2f} GB | {loader} | {result['error']} | | |")
                    continue
                assert result["rows"] == rows, result
                rate = size / 1e6 / result["seconds"] if result["seconds"] else math.inf
                print(f"| {hours:g} h | {rows:,} | {size / 1e9:.2f} GB | {loader} | {result['seconds']:.1f} | "
                      f"{rate:.0f} | {result['peak_mib']:.0f} |", flush=True)
        finally:
            shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
