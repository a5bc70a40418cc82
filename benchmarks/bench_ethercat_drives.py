"""Six emulated EtherCAT drives in one rtloop task at 1 kHz and at 4 kHz on one core, next to
cyclictest on the same core in the same run. Needs root (a veth pair, raw sockets, SCHED_FIFO).

For each period: a veth pair of its own; ``rtloop io emulate ethercat --app`` answering on one end,
pinned to ``--emulator-cpu`` at SCHED_FIFO 70; the JIWY EtherCAT example widened to six drives
(pan and tilt follow the trajectory, the four others hold their safe position) run for
``--duration-s`` with its task pinned to ``--cpu`` (priority 80) and ``timeout_us`` 90 % of the
period; ``cyclictest`` on the same CPU at priority 79 and the same interval, for the same time.
The figures: the task's cycles, deadline misses and latency (summary.json), how the run ended,
and cyclictest's samples, maximum and samples over the period.

Usage::

    sudo python benchmarks/bench_ethercat_drives.py --json benchmarks/results/ethercat-drives.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "jiwy_ethercat"


def six_drive_app(folder: Path, master: str, slave: str, period_us: int, drives: int) -> Path:
    """The example on this veth pair at ``period_us``, with ``drives`` drives: the extra ones copies of pan."""
    shutil.copy(EXAMPLE / "jiwy_trajectory.py", folder)
    text = (EXAMPLE / "jiwy_ethercat.toml").read_text()
    period_s = period_us / 1e6
    text = text.replace('name = "jiwy_ethercat"', f'name = "ecat{drives}x{period_us}"')
    text = text.replace('interface = "ecm0"', f'interface = "{master}"')
    text = text.replace('emulator_interface = "ecs0"', f'emulator_interface = "{slave}"')
    text = text.replace("period_ns = 1_000_000", f"period_ns = {period_us * 1000}")
    text = text.replace("period_s = 0.001", f"period_s = {period_s}")
    text = text.replace("cycle_s = 0.001", f"cycle_s = {period_s}")
    text = re.sub(r"timeout_us = \d+", f"timeout_us = {int(period_us * 0.9)}", text)
    pan = text[text.index("[[devices.gimbal.joints]]"):text.index("[[devices.gimbal.joints]]\nname = \"tilt\"")]
    extra = "".join(pan.replace('name = "pan"', f'name = "j{k}"') for k in range(3, drives + 1))
    at = text.index("[devices.gimbal.limits.pan_target_position_rad]")
    text = text[:at] + extra + text[at:]
    path = folder / f"ecat{drives}x{period_us}.toml"
    path.write_text(text)
    return path


def veth(tag: str) -> tuple[str, str]:
    master, slave = f"edm{tag}", f"eds{tag}"
    subprocess.run(["ip", "link", "add", master, "type", "veth", "peer", "name", slave], check=True)
    for name in (master, slave):
        subprocess.run(["ip", "link", "set", name, "up"], check=True)
    return master, slave


def one_period(period_us: int, args: argparse.Namespace, folder: Path) -> dict[str, object]:
    master, slave = veth(f"{os.getpid() % 10000:04d}{period_us % 100:02d}")
    try:
        app = six_drive_app(folder, master, slave, period_us, args.drives)
        log = folder / f"drives{period_us}.log"
        emulator = subprocess.Popen(["taskset", "-c", str(args.emulator_cpu), sys.executable, "-m", "rtloop", "io",
                                     "emulate", "ethercat", "--app", str(app), "--log", str(log), "--priority", "70"],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 60
        while not (log.exists() and "emulating" in log.read_text()) and time.monotonic() < deadline:
            time.sleep(0.05)
        out = folder / f"run{period_us}"
        cyclic_json = folder / f"cyclictest{period_us}.json"
        cyclic_command = ["cyclictest", "-m", "-q", "-t1", f"-a{args.cpu}", "-p79", f"-i{period_us}",
                          f"-D{round(args.duration_s)}", f"-h{4 * period_us}", f"--json={cyclic_json}"]
        cyclic = subprocess.Popen(cyclic_command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        run = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", str(args.duration_s),
                              "--cpu", str(args.cpu), "--out", str(out), "-q"], capture_output=True, text=True)
        cyclic_out, cyclic_err = cyclic.communicate(timeout=args.duration_s + 120)
        emulator.terminate()
        emulator.wait(timeout=30)
    finally:
        subprocess.run(["ip", "link", "del", master], capture_output=True)
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
    task = (summary.get("tasks") or {}).get("planner", {})
    histogram = [line.split() for line in cyclic_out.splitlines() if line[:1].isdigit()]
    over = sum(int(row[1]) for row in histogram if len(row) > 1 and int(row[0]) > period_us)
    overflow = re.search(r"# Histogram Overflows: (\d+)", cyclic_out)
    cyclic_result = json.loads(cyclic_json.read_text()) if cyclic_json.exists() else {}
    thread = next(iter((cyclic_result.get("thread") or {}).values()), {})
    return {"period_us": period_us, "drives": args.drives, "exit_code": run.returncode,
            "ended": next((line for line in run.stderr.splitlines() if line.startswith("rtloop run: task")),
                          run.stderr.strip()[:300] or "its duration")[:400],
            "cycles": task.get("cycles"), "deadline_misses": task.get("deadline_misses"),
            "overruns": task.get("overruns"), "latency_ns": task.get("latency_ns"),
            "cyclictest_samples": thread.get("cycles"), "cyclictest_max_us": thread.get("max"),
            "cyclictest_over_period": over + (int(overflow.group(1)) if overflow else 0),
            "cyclictest_stderr": cyclic_err.strip()[:300], "load": os.getloadavg()[0],
            "emulator_log_tail": log.read_text().splitlines()[-3:] if log.exists() else []}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--drives", type=int, default=6)
    parser.add_argument("--periods-us", default="1000,250")
    parser.add_argument("--duration-s", type=float, default=10.0)
    parser.add_argument("--cpu", type=int, default=0, help="the task's and cyclictest's CPU")
    parser.add_argument("--emulator-cpu", type=int, default=1)
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_ethercat_drives: needs root (a veth pair, raw sockets, SCHED_FIFO)", file=sys.stderr)
        return 2
    results = []
    with tempfile.TemporaryDirectory(prefix="ecat-drives-") as folder:
        for period_us in (int(p) for p in args.periods_us.split(",")):
            results.append(one_period(period_us, args, Path(folder)))
            print(json.dumps(results[-1], indent=1), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
