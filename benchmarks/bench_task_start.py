"""How long a run takes to start its task processes: forked from the task server vs spawned.

    .venv/bin/python benchmarks/bench_task_start.py --repeat 5 --json start.json    # ~1 min

Two ways a task process starts (runtime/task_start.py), alternating in one run, same machine
state: forked from the supervisor's task server, which imported the task's modules once (the
default), and spawned as a fresh interpreter that imports them itself (``RTLOOP_TASK_START=spawn``,
the way before). For each:

- a process that imports ``rtloop.runtime.task`` (what a task process imports, with numpy, to
  unpickle its entry point), from ``start()`` to its exit: the task server already running (it
  starts once per supervisor process, beside the supervisor's own imports: the next figures
  include it);
- ``rtloop run`` of a tiny app (one task, 1 ms period, ``--duration 1``) in a fresh process: the
  wall time of the whole command, start-up included (the server starts with the command);
- ``rtloop.run()`` called again in one Python process (a notebook, a test suite, a sweep): the
  wall time of each run after the first, the server already running.

The load average is given before and after: the wall times move with it, the difference between
the two ways in the same run is the figure to read.
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
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_output_options, closing_sections, machine_facts, markdown_table, print_and_save, result_head

WAYS = {"forked from the task server (now)": "", "spawned (before; RTLOOP_TASK_START=spawn)": "spawn"}
RUNNABLE = '''from rtloop import Runnable


class Tiny(Runnable):
    n_inputs = 1
    n_outputs = 1

    def step(self, u, y):
        y[0] = u[0] + 1.0
'''
APP = '''name = "{name}"
[tasks.tiny]
runnable = "tiny_start:Tiny"
period_ns = 1_000_000
'''
IN_PROCESS = '''import sys, time
sys.path.insert(0, {folder!r})
import rtloop
from rtloop.app.builder import App
from tiny_start import Tiny
times = []
for i in range({runs}):
    app = App("{name}")
    app.add_task("tiny", Tiny(), period_ns=1_000_000)
    started = time.perf_counter()
    rtloop.run(app, {duration_s}, {folder!r} + f"/in-process-{{i}}", force=True)
    times.append(time.perf_counter() - started)
print(times)
'''


ONE_START = '''import importlib, json, statistics, sys, time
from rtloop.runtime.task_start import task_context
context, server = task_context()
def started_and_ended():
    process = context.Process(target=importlib.import_module, args=("rtloop.runtime.task",))
    started = time.perf_counter()
    process.start()
    process.join()
    assert process.exitcode == 0, process.exitcode
    return time.perf_counter() - started
started_and_ended()  # the server's own preload is not a task's start
print(json.dumps([started_and_ended() for _ in range({repeat})]))
'''


def time_task_process_starts(way: str, repeat: int) -> list[float]:
    done = subprocess.run([sys.executable, "-c", ONE_START.format(repeat=repeat)], env=_environment(way),
                          capture_output=True, text=True, timeout=600)
    if done.returncode != 0:
        raise SystemExit(f"starting a process failed ({done.returncode}): {done.stderr.strip()[-400:]}")
    return [float(value) for value in json.loads(done.stdout.strip().splitlines()[-1])]


def _environment(way: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "RTLOOP_TASK_START"}
    if way:
        env["RTLOOP_TASK_START"] = way
    return env


def _rtloop() -> str:
    beside = Path(sys.executable).with_name("rtloop")
    return str(beside) if beside.exists() else "rtloop"


def time_cli_run(folder: Path, way: str, duration_s: float) -> float:
    command = [_rtloop(), "run", str(folder / "tiny.toml"), "--duration", str(duration_s), "--out",
               str(folder / "out"), "--force", "-q"]
    started = time.perf_counter()
    done = subprocess.run(command, env=_environment(way), capture_output=True, text=True, timeout=300)
    elapsed = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"rtloop run failed ({done.returncode}): {done.stderr.strip()[-400:]}")
    return elapsed


def time_runs_in_one_process(folder: Path, way: str, runs: int, duration_s: float, name: str) -> list[float]:
    code = IN_PROCESS.format(folder=str(folder), runs=runs, duration_s=duration_s, name=name)
    done = subprocess.run([sys.executable, "-c", code], env=_environment(way), capture_output=True, text=True,
                          timeout=600)
    if done.returncode != 0:
        raise SystemExit(f"rtloop.run() failed ({done.returncode}): {done.stderr.strip()[-400:]}")
    return [float(value) for value in json.loads(done.stdout.strip().splitlines()[-1])]


def run(args: argparse.Namespace) -> dict[str, Any]:
    facts = machine_facts()
    started = time.monotonic()
    load_before = os.getloadavg()
    name = f"bench_start_{os.getpid()}"
    one = {label: time_task_process_starts(way, args.repeat) for label, way in WAYS.items()}
    cli: dict[str, list[float]] = {way: [] for way in WAYS}
    again: dict[str, list[float]] = {way: [] for way in WAYS}
    with tempfile.TemporaryDirectory(prefix="rtloop-bench-start-") as work:
        folder = Path(work)
        (folder / "tiny_start.py").write_text(RUNNABLE)
        (folder / "tiny.toml").write_text(APP.format(name=name))
        for _ in range(args.repeat):
            for label, way in WAYS.items():
                cli[label].append(time_cli_run(folder, way, args.duration_s))
        for label, way in WAYS.items():  # the first run of the process starts the server: not counted
            again[label] = time_runs_in_one_process(folder, way, args.repeat + 1, args.duration_s, name)[1:]
    rows = [{"way": label, "process_start_median_s": statistics.median(one[label]), "process_start_s": one[label],
             "cli_run_median_s": statistics.median(cli[label]), "cli_run_s": cli[label],
             "run_again_median_s": statistics.median(again[label]), "run_again_s": again[label]}
            for label in WAYS]
    return {
        **result_head("task_start", args, facts, started),
        "load_average_before": list(load_before), "load_average_after": list(os.getloadavg()),
        "results": rows,
    }


def report_markdown(result: dict[str, Any]) -> str:
    duration_s = result["settings"]["duration_s"]
    starts = [[r["way"], f"{r['process_start_median_s'] * 1e3:.1f}",
               " ".join(f"{v * 1e3:.1f}" for v in r["process_start_s"])] for r in result["results"]]
    rows = [[r["way"], f"{r['cli_run_median_s']:.2f}", " ".join(f"{v:.2f}" for v in r["cli_run_s"]),
             f"{r['run_again_median_s']:.2f}", " ".join(f"{v:.2f}" for v in r["run_again_s"])]
            for r in result["results"]]
    load = (f"load average (1, 5, 15 min) before: {', '.join(f'{v:.2f}' for v in result['load_average_before'])}; "
            f"after: {', '.join(f'{v:.2f}' for v in result['load_average_after'])}")
    return "\n\n".join([
        "### A process importing rtloop.runtime.task, from start() to its exit (ms)",
        markdown_table(["task processes", "median", "each"], starts),
        f"### Wall time of a {duration_s:g} s run of a one-task app (s)",
        markdown_table(["task processes", f"`rtloop run --duration {duration_s:g}`: median", "each",
                        "`rtloop.run()` again in one process: median", "each"], rows),
        load,
        *closing_sections(result),
    ])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5, help="runs per way (each way's median is given)")
    parser.add_argument("--duration-s", type=float, default=1.0, help="each run's --duration")
    add_output_options(parser)
    args = parser.parse_args(argv)
    result = run(args)
    return print_and_save(report_markdown(result), result, args.json)


if __name__ == "__main__":
    raise SystemExit(main())
