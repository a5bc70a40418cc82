"""How long ``rtloop report`` takes to draw a run's figures and page: this tree beside an earlier one.

Each measurement is a fresh Python process (as ``rtloop report`` is) that imports the report engine
and then times one ``build_report`` of the given run directories into a folder of its own: wall
time and the process's CPU time (CPU time moves less with the other load of a shared machine).
The earlier tree is a ``src`` folder of another commit, put beside this one::

    git archive COMMIT src | tar -x -C /tmp/earlier
    python benchmarks/bench_report.py runs/jiwy --reference-src /tmp/earlier/src --rounds 5

Rounds alternate the two trees, so both see the same moments of the machine's load.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import add_output_options, closing_sections, machine_facts, markdown_table, print_and_save, result_head

THIS_SRC = Path(__file__).resolve().parents[1] / "src"
CHILD = """
import json, sys, time
from pathlib import Path
from rtloop.report.build import build_report
runs, out = [Path(p) for p in sys.argv[2:]], Path(sys.argv[1])
wall, cpu = time.perf_counter(), time.process_time()
report = build_report(runs, out)
print(json.dumps({"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
                  "figures": len(report.pngs), "engine": __import__("rtloop").__file__}))
"""


def measure(src: Path, runs: list[Path], out: Path) -> dict[str, float]:
    """One ``build_report`` of ``runs`` by the rtloop in ``src``, in a process of its own."""
    env = {**os.environ, "PYTHONPATH": str(src)}
    done = subprocess.run([sys.executable, "-c", CHILD, str(out), *map(str, runs)], env=env, capture_output=True,
                          text=True, timeout=600, check=False)
    if done.returncode != 0:
        raise SystemExit(f"bench_report: the report by {src} failed: {done.stderr.strip().splitlines()[-1:]}")
    result: dict[str, float] = json.loads(done.stdout.strip().splitlines()[-1])
    if not str(result["engine"]).startswith(str(src)):
        raise SystemExit(f"bench_report: {src} was not the rtloop imported ({result['engine']})")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories, drawn into one report")
    parser.add_argument("--reference-src", type=Path, help="the src folder of an earlier tree, measured beside")
    parser.add_argument("--rounds", type=int, default=5, help="reports per tree, the trees alternating")
    add_output_options(parser)
    args = parser.parse_args(argv)
    started = time.monotonic()
    facts = machine_facts()
    trees = {"this tree": THIS_SRC}
    if args.reference_src is not None:
        trees = {"reference": args.reference_src.resolve(), **trees}
    samples: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
    with tempfile.TemporaryDirectory(prefix="bench_report-") as folder:
        for round_index in range(args.rounds):
            for name, src in trees.items():
                samples[name].append(measure(src, args.runs, Path(folder) / f"{name}-{round_index}"))
    rows = []
    for name, measured in samples.items():
        wall = [m["wall_s"] for m in measured]
        cpu = [m["cpu_s"] for m in measured]
        rows.append([name, int(measured[0]["figures"]), statistics.median(wall), min(wall),
                     statistics.median(cpu), min(cpu)])
    head = result_head("bench_report", args, facts, started)
    head["settings"] = {"runs": [run.name for run in args.runs], "rounds": args.rounds}  # no paths of this machine
    head["command"] = f"bench_report.py {' '.join(run.name for run in args.runs)} --rounds {args.rounds}" + (
        " --reference-src EARLIER/src" if args.reference_src is not None else "")
    result = {**head, "results": {name: [{k: v for k, v in m.items() if k != "engine"} for m in measured]
                                  for name, measured in samples.items()}}
    table = markdown_table(["tree", "figures", "wall s (median)", "wall s (min)", "CPU s (median)",
                            "CPU s (min)"], rows)
    heading = f"## rtloop report of {', '.join(run.name for run in args.runs)}, {args.rounds} rounds each"
    markdown = "\n\n".join([heading, table, *closing_sections(result)])
    return print_and_save(markdown, result, args.json)


if __name__ == "__main__":
    raise SystemExit(main())
