"""Soak: JIWY runs until stopped (no --duration, --keep 60) beside cyclictest on the same core.

    sudo python benchmarks/bench_soak.py --minutes 30

What it does:

- starts ``rtloop run`` on a copy of ``examples/jiwy/jiwy.toml`` (its ROS 2 section left out,
  a unique app name, the step setpoint profile fed in) with ``--keep 60`` and no
  ``--duration``, every task pinned to ``--cpu``;
- starts ``cyclictest`` for the same time on the same CPU, one thread, 1 ms interval,
  mlockall, SCHED_FIFO at ``--cyclictest-priority`` (default 79: just below JIWY's tasks at
  80 and 81, so it measures the wake-up latency a lower-priority RT thread sees on a core
  that runs JIWY; JIWY's numbers are not disturbed by it);
- every ``--sample-s`` seconds reads VmRSS of the supervisor and of each task process from
  /proc, the disk used by the run folder and the live ``summary.json`` (cycles, misses);
- after ``--minutes``, stops the run with SIGINT, reads the final summary and cyclictest's
  JSON, prints a markdown table and writes everything to ``benchmarks/results/``.

RSS growth is measured from the sample at ``--warmup-s`` (by then the 60 s window has
rotated its segments and every buffer has reached its size) to the last sample.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
JIWY = ROOT / "examples" / "jiwy"
RESULTS = Path(__file__).resolve().parent / "results"


def app_file(folder: Path, name: str) -> Path:
    """jiwy.toml with a unique name and without its [ros] tables (no DDS traffic in a soak)."""
    text = (JIWY / "jiwy.toml").read_text()
    text = re.sub(r'^name = "jiwy"$', f'name = "{name}"', text, flags=re.M)
    text = text.split("[[ros.")[0]
    path = folder / f"{name}.toml"
    path.write_text(text)
    return path


def rss_kib(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def task_pids(name: str, supervisor: int) -> dict[str, int]:
    """The supervisor's task processes (keyed pidN, as the results have them), from the running app's
    own registry: each task's status block holds its pid, however the process was started."""
    from rtloop.ipc.ports import running_apps

    for app in running_apps():
        if app.name == name and app.pid == supervisor:
            return {f"pid{pid}": pid for pid in app.task_pids().values() if pid}
    return {}


def disk_bytes(folder: Path) -> int:
    total = 0
    for path in folder.rglob("*"):
        try:
            if path.is_file():
                total += path.stat().st_size
        except OSError:
            pass
    return total


def read_summary(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--cpu", type=int, default=max(os.sched_getaffinity(0)))
    parser.add_argument("--keep", type=float, default=60.0)
    parser.add_argument("--sample-s", type=float, default=10.0)
    parser.add_argument("--warmup-s", type=float, default=120.0)
    parser.add_argument("--cyclictest-priority", type=int, default=79)
    parser.add_argument("--label", default=dt.date.today().isoformat() + "-soak")
    args = parser.parse_args()

    duration_s = args.minutes * 60
    folder = Path(tempfile.mkdtemp(prefix="rtloop-soak-"))
    name = f"jiwy_soak_{os.getpid()}"
    out = folder / "run"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT / "src"), str(JIWY), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    command = [sys.executable, "-m", "rtloop.cli", "run", str(app_file(folder, name)), "--keep", f"{args.keep:g}",
               "--out", str(out), "--cpu", str(args.cpu), "--feed", f"setpoint={JIWY / 'setpoints' / 'step.csv'}",
               "-q"]
    cyclictest_json = folder / "cyclictest.json"
    cyclictest = ["cyclictest", "-m", "-q", "-t1", f"-a{args.cpu}", f"-p{args.cyclictest_priority}", "-i1000",
                  f"-D{round(duration_s)}", f"--json={cyclictest_json}"]
    print(f"soak {args.minutes:g} min, cpu {args.cpu}, folder {folder}", flush=True)
    rtloop_log = open(folder / "rtloop.log", "w")  # noqa: SIM115
    supervisor = subprocess.Popen(command, env=env, stdout=rtloop_log, stderr=subprocess.STDOUT)
    cyclic = subprocess.Popen(cyclictest, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    started = time.monotonic()
    samples: list[dict] = []
    try:
        while time.monotonic() - started < duration_s and supervisor.poll() is None:
            time.sleep(args.sample_s)
            summary = read_summary(out / "summary.json") or {}
            tasks = {n: rss_kib(p) for n, p in task_pids(name, supervisor.pid).items()}
            sample = {
                "t_s": round(time.monotonic() - started, 1),
                "supervisor_rss_kib": rss_kib(supervisor.pid),
                "task_rss_kib": tasks,
                "disk_bytes": disk_bytes(out),
                "cycles": {n: t.get("cycles") for n, t in summary.get("tasks", {}).items()},
                "deadline_misses": {n: t.get("deadline_misses") for n, t in summary.get("tasks", {}).items()},
            }
            samples.append(sample)
            print(json.dumps(sample), flush=True)
    finally:
        if supervisor.poll() is None:
            supervisor.send_signal(signal.SIGINT)
        supervisor.wait(timeout=120)
        cyclic.wait(timeout=120 + duration_s)
    final = read_summary(out / "summary.json") or {}
    cyclic_result = read_summary(cyclictest_json) or {}
    result = {
        "label": args.label,
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),  # no machine paths in results
        "cyclictest_command": " ".join(cyclictest),
        "minutes": args.minutes,
        "cpu": args.cpu,
        "exit_code": supervisor.returncode,
        "samples": samples,
        "final_summary": final,
        "final_disk_bytes": disk_bytes(out),
        "final_files": {p.name: p.stat().st_size for p in out.iterdir() if p.is_file()} if out.exists() else {},
        "cyclictest": cyclic_result,
        "cyclictest_stderr": cyclic.stderr.read() if cyclic.stderr else "",
    }
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{args.label}.json"
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(report(result, args.warmup_s))
    print(f"raw results: {path}")
    return 0


def report(result: dict, warmup_s: float) -> str:
    samples = result["samples"]
    if not samples:
        return "no samples"
    first, last = samples[0], samples[-1]
    warm = next((s for s in samples if s["t_s"] >= warmup_s), first)
    lines = ["| | start | after warm-up | end | growth after warm-up |", "|---|---|---|---|---|"]

    def row(label: str, pick) -> None:
        values = [pick(s) for s in (first, warm, last)]
        if None in values:
            return
        lines.append(f"| {label} | {values[0] / 1024:.1f} MiB (t={first['t_s']:.0f} s) | {values[1] / 1024:.1f} MiB "
                     f"(t={warm['t_s']:.0f} s) | {values[2] / 1024:.1f} MiB (t={last['t_s']:.0f} s) | "
                     f"{(values[2] - values[1]) / 1024:+.2f} MiB |")

    row("supervisor RSS", lambda s: s["supervisor_rss_kib"])
    for task in first["task_rss_kib"]:
        row(f"task process {task} RSS", lambda s, t=task: s["task_rss_kib"].get(t))
    disk = [s["disk_bytes"] for s in samples]
    lines.append(f"| run folder on disk | {disk[0] / 2**20:.1f} MiB | | {disk[-1] / 2**20:.1f} MiB "
                 f"(max {max(disk) / 2**20:.1f} MiB; after the stop {result['final_disk_bytes'] / 2**20:.1f} MiB) | |")
    lines.append("")
    final = result["final_summary"]
    for name, task in final.get("tasks", {}).items():
        latency = task["latency_ns"]
        lines.append(f"- rtloop task {name}: {task['cycles']} cycles, {task['deadline_misses']} deadline misses, "
                     f"{task['overruns']} overruns, latency p50/p99/p99.9/max "
                     f"{latency['p50'] / 1e3:.1f}/{latency['p99'] / 1e3:.1f}/{latency['p999'] / 1e3:.1f}/"
                     f"{latency['max'] / 1e3:.1f} µs, longest run of misses {task.get('misses_in_a_row_max')}")
    threads = result["cyclictest"].get("thread", {})
    for thread in threads.values():
        lines.append(f"- cyclictest (prio {result['cyclictest_command'].split('-p')[1].split()[0]}, same CPU): "
                     f"{thread.get('cycles')} cycles, latency min/avg/max {thread.get('min')}/{thread.get('avg')}/"
                     f"{thread.get('max')} µs")
    lines.append(f"- rtloop exit code {result['exit_code']}, stopped by {final.get('stopped_by')}, "
                 f"recording {final.get('recording')}")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
