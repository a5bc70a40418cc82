"""How long Ctrl-C takes to end a run whose busy tasks starve the supervisor (issue 19's starvation case).

    tools/as-root .venv/bin/python benchmarks/bench_stop.py [--runs N] [--run-s S] [--rate HZ]

Two tasks at 50 kHz (``Counter`` runnables, everything recorded), one per processor at
SCHED_FIFO 70 and 60, above the supervisor: ``rtloop run`` without a duration (so with the
CLI's default ``--keep 60``), SIGINT after ``--run-s`` seconds, and the time from the signal
to the command's exit. Beside it, in each run, what the summary says was lost (records the
queues dropped during the run, and what was left unwritten at the stop).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parent.parent / "tests"  # rt_test_runnables


def app_file(folder: Path, name: str, period_ns: int) -> Path:
    cpus = sorted(os.sched_getaffinity(0))[-2:]
    tasks = "".join(f'[tasks.{task}]\nrunnable = "rt_test_runnables:Counter"\nperiod_ns = {period_ns}\n'
                    f"priority = {priority}\ncpu = {cpu}\n"
                    for task, priority, cpu in (("a", 70, cpus[0]), ("b", 60, cpus[-1])))
    path = folder / "app.toml"
    path.write_text(f'name = "{name}"\n{tasks}[record]\nsignals = ["a.y", "b.y"]\n')
    return path


def one_stop(folder: Path, run_s: float, period_ns: int) -> dict[str, object]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(TESTS), os.environ.get("PYTHONPATH")])))
    out = folder / "out"
    app = app_file(folder, f"bench_stop_{os.getpid()}", period_ns)
    process = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app), "--out", str(out), "--force"],
                               env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(run_s)
    sent_at = time.monotonic()
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=300)
    stop_s = time.monotonic() - sent_at
    if process.returncode != 0:
        sys.exit(f"bench_stop: the run failed: {stderr.strip()[-500:]}")
    lost = json.loads((out / "summary.json").read_text())["recording"]["lost"]
    return {"stop_s": stop_s, **{kind: sum(counts.values()) for kind, counts in lost.items()}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--run-s", type=float, default=5.0, help="seconds from start to SIGINT")
    parser.add_argument("--rate", type=int, default=50_000, help="each task's rate, Hz")
    args = parser.parse_args(argv)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.runs):
            results.append(one_stop(Path(tmp), args.run_s, round(1e9 / args.rate)))
    print(f"stop of a starved run: 2 tasks at {args.rate} Hz, SIGINT after {args.run_s:g} s, "
          f"load average {os.getloadavg()[0]:.1f}")
    kinds = [k for k in results[0] if k != "stop_s"]
    print("| SIGINT → exit (s) | " + " | ".join(f"lost {k}" for k in kinds) + " |")
    print("|---|" + "---|" * len(kinds))
    for r in results:
        print(f"| {r['stop_s']:.2f} | " + " | ".join(str(r[k]) for k in kinds) + " |")
    stops = sorted(float(r["stop_s"]) for r in results)  # type: ignore[arg-type]
    print(f"median {stops[len(stops) // 2]:.2f} s, max {stops[-1]:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
