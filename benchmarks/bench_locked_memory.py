"""Memory locked per task process: everything locked up front vs locked on fault + what the loop touches.

    sudo .venv/bin/python benchmarks/bench_locked_memory.py --json locked.json    # ~1 min

Runs a no-op task and the JIWY example (two task processes) with the two ways a task locks its
memory, alternating in one run:

- ``mlockall(MCL_CURRENT|MCL_FUTURE)``: every page of every mapping read in and locked (rtloop before
  this change; ``RTLOOP_LOCK_ALL_MEMORY=1`` today);
- ``mlockall(...|MCL_ONFAULT)`` + ``lock_what_the_loop_touches`` before T0 (linux/lean.py): the
  default.

For each task process, once its loop runs: the resident pages of its locked mappings (``Rss`` of
the mappings with ``lo`` in ``/proc/PID/smaps``, rtloop.linux.memory.locked_bytes: what mlock holds in
RAM for it, shared library pages counted whole: the figure the target is about), ``Locked`` of
``/proc/PID/smaps_rollup`` (the same pages as a proportional share: a page shared by the JIWY's two
tasks and the supervisor counts a third), ``VmLck`` of ``/proc/PID/status`` (the size of the locked
mappings, touched or not: it does not move with MCL_ONFAULT), ``VmRSS``, and the page faults
(minor + major) the task's thread took over a window of its loop (``/proc/PID/task/PID/stat``).
Memory figures do not depend on the machine's load; the fault counts should be 0 either way.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_output_options, closing_sections, machine_facts, markdown_table, print_and_save, result_head

from rtloop.ipc.ports import connect_app
from rtloop.ipc.schema import STATUS_WORDS
from rtloop.ipc.status import StatusWord, TaskState, WordBlock
from rtloop.linux.memory import locked_bytes
from rtloop.linux.rt import LOCK_ALL_MEMORY_ENV

HERE = Path(__file__).resolve().parent
JIWY = HERE.parent / "examples" / "jiwy"
MODES = {"everything up front: MCL_CURRENT + MCL_FUTURE (before)": "1",
         "MCL_ONFAULT, the loop's memory locked in full before T0 (now)": "0"}
TARGET_MB = 60.0


def app_text(kind: str, name: str) -> str:
    if kind == "no-op":
        return f'name = "{name}"\n[tasks.t]\nrunnable = "_common:NoOp"\nperiod_ns = 1_000_000\ncpu = 1\n'
    text = (JIWY / "jiwy.toml").read_text()
    text = text.replace('name = "jiwy"', f'name = "{name}"', 1)
    return text.split("# ROS 2 topics")[0]  # the loop's memory, not the bridges' (separate processes anyway)


def _kib(path: Path, field: str) -> float:
    for line in path.read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def thread_faults(pid: int) -> int:
    """minflt + majflt of the task's main thread (the loop's thread)."""
    fields = Path(f"/proc/{pid}/task/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[7]) + int(fields[9])  # fields 10 and 12 of stat(5), counted after the ")"


def measure(kind: str, lock_all: str, work: Path, window_s: float, index: int) -> list[dict[str, Any]]:
    name = f"bench_locked_{os.getpid()}_{index}"
    app_file = work / f"{name}.toml"
    app_file.write_text(app_text(kind, name))
    env = {**os.environ, LOCK_ALL_MEMORY_ENV: lock_all,
           "PYTHONPATH": os.pathsep.join([str(HERE), str(JIWY), *sys.path])}
    process = subprocess.Popen([sys.executable, "-m", "rtloop.cli", "run", str(app_file), "--duration",
                                str(window_s + 4), "--out", str(work / name)], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    rows = []
    try:
        app = connect_app(name, timeout_s=30)
        segments = app.registry["tasks"]
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            states = [WordBlock(app.segment(s), 0, STATUS_WORDS)[StatusWord.STATE] for s in segments.values()]
            if all(state == TaskState.RUNNING for state in states):
                break
            time.sleep(0.05)
        time.sleep(0.5)  # some cycles first: what the first ones touch counts too
        pids = app.task_pids()
        before = {task: thread_faults(pid) for task, pid in pids.items()}
        time.sleep(window_s)
        for task, pid in pids.items():
            faults = thread_faults(pid) - before[task]
            proc = Path(f"/proc/{pid}")
            rows.append({"app": kind, "task": task, "locked_resident_MB": (locked_bytes(pid) or 0) / 2**20,
                         "locked_proportional_MB": _kib(proc / "smaps_rollup", "Locked"),
                         "VmLck_MB": _kib(proc / "status", "VmLck"), "VmRSS_MB": _kib(proc / "status", "VmRSS"),
                         "faults_in_window": faults, "window_s": window_s})
    finally:
        if process.poll() is None:  # measured (or given up): Ctrl-C ends the run, its duration is only a bound
            process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=60)
    if process.returncode != 0:
        raise SystemExit(f"{kind} run failed ({process.returncode}): {stderr.strip()[-400:]}")
    return rows


def run(args: argparse.Namespace) -> dict[str, Any]:
    facts = machine_facts()
    started = time.monotonic()
    results: dict[str, list[dict[str, Any]]] = {mode: [] for mode in MODES}
    with tempfile.TemporaryDirectory(prefix="rtloop-bench-locked-") as work:
        index = 0
        for _ in range(args.rounds):
            for kind in ("no-op", "JIWY"):
                for mode, lock_all in MODES.items():
                    results[mode] += measure(kind, lock_all, Path(work), args.window_s, index)
                    index += 1
    worst = max(row["locked_resident_MB"] for row in results[list(MODES)[1]])
    return {
        **result_head("locked_memory", args, facts, started),
        "results": results,
        "targets": [{"target": f"memory locked (and resident) per task process ≤ {TARGET_MB:.0f} MB",
                     "measured": f"{worst:.1f} MB (largest task process)", "met": bool(worst <= TARGET_MB)}],
    }


def report_markdown(result: dict[str, Any]) -> str:
    rows = [[mode, r["app"], r["task"], r["locked_resident_MB"], r["locked_proportional_MB"], r["VmLck_MB"],
             r["VmRSS_MB"],
             f"{r['faults_in_window']} in {r['window_s']:g} s"]
            for mode, found in result["results"].items() for r in found]
    return "\n\n".join([
        "### Memory per task process (MB), while its loop runs",
        markdown_table(["locking", "app", "task", "locked + resident", "its proportional share", "VmLck", "VmRSS",
                        "thread's page faults"], rows),
        *closing_sections(result),
    ])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--window-s", type=float, default=5.0, help="loop time over which faults are counted")
    add_output_options(parser)
    args = parser.parse_args(argv)
    result = run(args)
    return print_and_save(report_markdown(result), result, args.json)


if __name__ == "__main__":
    raise SystemExit(main())
