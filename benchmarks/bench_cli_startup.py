"""How long ``rtloop`` takes to answer before any work: help, a usage error, ``port write``.

Each command line runs in a fresh interpreter, ``--repeat`` times, interleaved with two
references in the same run: ``python -c pass`` (the interpreter alone) and ``python -c
"import rtloop"`` (the package every command imports first). For each it gives the median
wall time and how many modules were imported (``-X importtime``; the count does not depend
on the machine's load, the time does), and which heavy ones among them (matplotlib, rich,
DDS, the supervisor). ``--compare SRC`` runs the same command lines against another
source tree in the same run (e.g. the commit before a change, from ``git archive``).

    python benchmarks/bench_cli_startup.py
    git archive REV src | tar -x -C /tmp/before && python benchmarks/bench_cli_startup.py --compare /tmp/before/src
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
COMMANDS = [
    ["--help"],
    ["run", "--help"],
    ["report", "--help"],
    ["top", "--help"],
    ["bridge", "--help"],
    ["service", "--help"],
    ["bench", "--help"],
    ["top", "--interval", "0"],  # a usage error
    ["port", "write", "no_such_app_bench", "setpoint", "1"],  # refused: no such app (exit 2)
]
REFERENCES = {"python -c pass": ["-c", "pass"], "python -c 'import rtloop'": ["-c", "import rtloop"]}
HEAVY = ("matplotlib", "rich", "cyclonedds", "mcap", "rtloop.report.build", "rtloop.ros.bridge",
         "rtloop.runtime.supervisor")


def measure(arguments: list[str], src: Path, repeat: int) -> tuple[float, int, list[str]]:
    """(median wall seconds, modules imported, heavy modules among them) of ``python ARGUMENTS``."""
    env = {**os.environ, "PYTHONPATH": str(src)}
    times = []
    for _ in range(repeat):
        started = time.perf_counter()
        subprocess.run([sys.executable, *arguments], env=env, capture_output=True, check=False)
        times.append(time.perf_counter() - started)
    traced = subprocess.run([sys.executable, "-X", "importtime", *arguments], env=env, capture_output=True,
                            text=True, check=False)
    names = [line.rsplit("|", 1)[-1].strip() for line in traced.stderr.splitlines()
             if line.startswith("import time:") and not line.rstrip().endswith("package")]
    heavy = [name for name in HEAVY if name in names]
    return statistics.median(times), len(names), heavy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=9, help="runs per command line (default 9)")
    parser.add_argument("--compare", type=Path, default=None, metavar="SRC",
                        help="another source tree, measured side by side (its 'before' column)")
    parser.add_argument("--json", type=Path, default=None, metavar="PATH", help="also write every figure here")
    args = parser.parse_args()
    results: list[dict[str, object]] = []
    trees = {"this tree": SRC} if args.compare is None else {"compare": args.compare, "this tree": SRC}
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs, median of {args.repeat} runs; "
          "modules: how many -X importtime lists")
    print("| command line | " + " | ".join(f"{name}: ms, modules, heavy" for name in trees) + " |")
    print("|---|" + "---|" * len(trees))
    rows = [(label, arguments) for label, arguments in REFERENCES.items()]
    rows += [("rtloop " + " ".join(command), ["-m", "rtloop.cli", *command]) for command in COMMANDS]
    for label, arguments in rows:
        cells = []
        for tree, src in trees.items():
            wall_s, modules, heavy = measure(arguments, src, args.repeat)
            cells.append(f"{wall_s * 1e3:.0f} ms, {modules}, {', '.join(heavy) or '-'}")
            results.append({"command": label, "tree": tree, "median_wall_s": wall_s, "modules": modules,
                            "heavy": heavy})
        print(f"| `{label}` | " + " | ".join(cells) + " |", flush=True)
    if args.json is not None:
        machine = {"python": sys.version.split()[0], "cpus": os.cpu_count(), "platform": platform.platform(),
                   "load_average": os.getloadavg(), "repeat": args.repeat}
        args.json.write_text(json.dumps({"machine": machine, "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
