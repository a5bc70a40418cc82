"""Six emulated EtherCAT drives in one rtloop task at 1 kHz and at 4 kHz on one core, next to
cyclictest on the same core in the same run. Needs root (a veth pair, raw sockets, SCHED_FIFO).

First, how long the emulated drives take to answer one cycle frame (the LRW of six drives and the
FRMW of the DC reference clock's time, as rtloop sends it): in process, through the compiled path
and through the Python reference; and on a veth pair, the round trip from a master at SCHED_FIFO
80 on ``--cpu`` through the emulator on ``--emulator-cpu``, next to the same frame through a bare
echo (a raw socket that sends back what it receives, the same CPU and priority): what the emulator
adds to the wire's and the wake-ups' share. So a reader sees the emulator is not what is measured.

Then for each period and each ``--lost-frames-ms`` budget: a veth pair of its own
(``rtloop.io.drives.veth``); ``rtloop io emulate ethercat --app`` answering on one end, pinned to
``--emulator-cpu`` at SCHED_FIFO 70; the JIWY EtherCAT example widened to six drives (pan and tilt
follow the trajectory, the four others hold their position; ``tests/drive_veth.py``'s
``example_app``) run for ``--duration-s`` with its task pinned to ``--cpu`` (priority 80) and
``timeout_us`` 90 % of the period, and ``lost_frames_max`` so that the drives run at most the
budget without their frame ((N + 1) periods; at most 254 frames: the datagram index);
``cyclictest`` on the same CPU at priority 79 and the same interval, for the same time. The
budgets: 10 ms, what a master on a real segment could well allow, so a 30-60 ms stall of this VM
still faults; and 90 ms, the most the example's 100 ms SM watchdog allows, so the VM's stalls of
the emulated drives' CPU (which a segment of real ESCs, forwarding in hardware, does not have) are
ridden out and counted, and misses can be counted over the whole run. The figures: the task's
cycles, deadline misses, release latency and execution time, the lost frames and the longest run of
them (summary.json), how the run ended, and cyclictest's samples, maximum and samples over the
period; the load average before each run. The last lines are the rows for BENCHMARKS.md.

Usage (re-run on a quiet machine; ``--json`` keeps the figures)::

    sudo .venv/bin/python benchmarks/bench_ethercat_drives.py --json benchmarks/results/ethercat-drives.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from drive_veth import example_app
from rtloop.io import compiled
from rtloop.io.drives.veth import VethError, veth_pair, veth_problem
from test_drive_esc_compiled import Side, configuration_frames, cycle_frame

WATCHDOG = "watchdog_ms = 100"  # the example's SM watchdog: lost_frames_max goes after it


def answer_time_us(use_compiled: bool, frames: int, batches: int = 5) -> dict[str, float]:
    """µs per cycle frame (six drives, LRW + FRMW) through Segment.process and its tick, in process:
    the best and the median of ``batches`` batches."""
    side = Side(use_compiled)
    for frame in configuration_frames():
        side.send(bytearray(frame))
    cycle = [cycle_frame(k) for k in range(frames)]  # the enabling, then CSP, CSV and CST motion
    per_frame = []
    for _ in range(batches):
        start = time.perf_counter_ns()
        for frame in cycle:
            side.segment.process(frame)
            side.segment.tick(side.clock.ns)
            side.clock.ns += 250_000
        per_frame.append((time.perf_counter_ns() - start) / frames / 1000)
    return {"best_us": min(per_frame), "median_us": statistics.median(per_frame)}


ECHO = """
from rtloop.io.drives.rawsocket import open_raw
sock, buffer = open_raw({slave!r}, timeout_s=0.001), bytearray(2048)
while True:
    try:
        size = sock.recv_into(buffer)
    except TimeoutError:
        continue
    if buffer[12:14] == b"\\x88\\xa4":
        sock.send(memoryview(buffer)[:size])
"""


def round_trip_us(answerer: str, args: argparse.Namespace, folder: Path, frames: int = 3000) -> dict[str, float]:
    """The cycle frame's round trip on a veth pair of its own through ``echo`` or ``emulator`` (six
    default drives), from this process at SCHED_FIFO 80 on ``args.cpu``, one frame each 500 µs."""
    from rtloop.io.drives.rawsocket import open_raw

    tag = f"{os.getpid() % 10000:04d}{answerer[:2]}"
    with veth_pair(f"erm{tag}", f"ers{tag}") as (master, slave):
        pin = ["taskset", "-c", str(args.emulator_cpu)]
        if answerer.startswith("echo"):
            child = subprocess.Popen([*pin, "chrt", "-f", "70", sys.executable, "-c", ECHO.format(slave=slave)])
        else:
            log = folder / f"rtt-{tag}.log"
            child = subprocess.Popen([*pin, sys.executable, "-m", "rtloop", "io", "emulate", "ethercat", "--slaves",
                                      "6", "--interface", slave, "--priority", "70", "--log", str(log)])
        try:
            time.sleep(2.0)  # the child's start (the emulator's imports)
            sock = open_raw(master, timeout_s=0.01)
            frame, reply = cycle_frame(5), bytearray(2048)
            affinity = os.sched_getaffinity(0)
            os.sched_setaffinity(0, {args.cpu})
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
            rtts = []
            try:
                for _ in range(frames):
                    start = time.perf_counter_ns()
                    sock.send(frame)
                    try:
                        sock.recv_into(reply)
                    except TimeoutError:
                        continue
                    rtts.append((time.perf_counter_ns() - start) / 1000)
                    time.sleep(0.0005)
            finally:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
                os.sched_setaffinity(0, affinity)
                sock.close()
        finally:
            child.terminate()
            child.wait(timeout=30)
    rtts.sort()
    return {"answered": len(rtts), "sent": frames, "min_us": rtts[0], "p50_us": rtts[len(rtts) // 2],
            "p99_us": rtts[int(len(rtts) * 0.99)], "max_us": rtts[-1]}


def steal_ms(cpus: tuple[int, ...]) -> dict[int, float]:
    """Each CPU's steal time so far (/proc/stat, ms): the hypervisor running something else."""
    ticks = os.sysconf("SC_CLK_TCK")
    found = {}
    for line in Path("/proc/stat").read_text().splitlines():
        name, *fields = line.split()
        if name.startswith("cpu") and name[3:].isdigit() and int(name[3:]) in cpus and len(fields) > 7:
            found[int(name[3:])] = int(fields[7]) * 1000 / ticks
    return found


INDEX_FRAMES_MAX = 254
"""The most lost frames in a row the datagram index allows (io/drives/ethercat_lost.py)."""


def lost_frames_max(period_us: int, budget_ms: float) -> int:
    """The most lost frames in a row with the drives at most ``budget_ms`` without their frame
    ((N + 1) periods, below the SM watchdog), and the datagram index's bound."""
    return max(0, min(INDEX_FRAMES_MAX, round(budget_ms * 1000 / period_us) - 1))


def one_period(period_us: int, budget_ms: float, args: argparse.Namespace, folder: Path) -> dict[str, Any]:
    tag = f"{os.getpid() % 1000:03d}{period_us % 100:02d}{round(budget_ms) % 100:02d}"
    started = time.strftime("%H:%M", time.gmtime())  # UTC, in the row
    load = os.getloadavg()[0]
    cpus = (args.cpu, args.emulator_cpu)
    steal_before = steal_ms(cpus)
    lost_max = lost_frames_max(period_us, budget_ms)
    with veth_pair(f"edm{tag}", f"eds{tag}") as (master, slave):
        app = example_app(folder, master, slave, f"ecat{args.drives}x{period_us}_{tag}", period_us / 1000,
                          args.drives, **{WATCHDOG: f"{WATCHDOG}\nlost_frames_max = {lost_max}"})
        log = folder / f"drives{period_us}-{tag}.log"
        emulator = subprocess.Popen(["taskset", "-c", str(args.emulator_cpu), sys.executable, "-m", "rtloop", "io",
                                     "emulate", "ethercat", "--app", str(app), "--log", str(log), "--priority", "70"],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 60
        while not (log.exists() and "emulating" in log.read_text()) and time.monotonic() < deadline:
            time.sleep(0.05)
        out = folder / f"run{tag}"
        cyclic_json = folder / f"cyclictest{tag}.json"
        cyclic_command = ["cyclictest", "-m", "-q", "-t1", f"-a{args.cpu}", "-p79", f"-i{period_us}",
                          f"-D{round(args.duration_s)}", f"-h{4 * period_us}", f"--json={cyclic_json}"]
        cyclic = subprocess.Popen(cyclic_command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        run = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", str(args.duration_s),
                              "--cpu", str(args.cpu), "--out", str(out), "-q"], capture_output=True, text=True)
        cyclic_out, cyclic_err = cyclic.communicate(timeout=args.duration_s + 120)
        emulator.terminate()
        emulator.wait(timeout=30)
    steal_after = steal_ms(cpus)
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
    task = (summary.get("tasks") or {}).get("planner", {})
    device = (summary.get("devices") or {}).get("gimbal", {})
    lost_note = next((note for note in summary.get("notes") or [] if "lost_frames_max =" in note), "")
    in_a_row = re.search(r"at most (\d+) in a row", lost_note)  # the device's count: exchanges, not releases
    histogram = [line.split() for line in cyclic_out.splitlines() if line[:1].isdigit()]
    over = sum(int(row[1]) for row in histogram if len(row) > 1 and int(row[0]) > period_us)
    overflow = re.search(r"# Histogram Overflows: (\d+)", cyclic_out)
    cyclic_result = json.loads(cyclic_json.read_text()) if cyclic_json.exists() else {}
    thread = next(iter((cyclic_result.get("thread") or {}).values()), {})
    emulator_log = log.read_text() if log.exists() else ""
    return {"period_us": period_us, "started": started, "drives": args.drives, "lost_frames_max": lost_max,
            "blind_ms": (lost_max + 1) * period_us / 1000, "exit_code": run.returncode,
            "ended": next((line for line in run.stderr.splitlines() if line.startswith("rtloop run: task")),
                          run.stderr.strip()[:300] or "its duration")[:400],
            "cycles": task.get("cycles"), "deadline_misses": task.get("deadline_misses"),
            "overruns": task.get("overruns"), "latency_ns": task.get("latency_ns"), "exec_ns": task.get("exec_ns"),
            "lost_frames": device.get("stale_reads"), "lost_in_a_row_max": int(in_a_row.group(1)) if in_a_row else None,
            "first_lost_cycles": (device.get("first_stale_cycles") or [])[:10],
            "cyclictest_samples": thread.get("cycles"), "cyclictest_max_us": thread.get("max"),
            "cyclictest_over_period": over + (int(overflow.group(1)) if overflow else 0),
            "cyclictest_stderr": cyclic_err.strip()[:300], "load_before": load, "load_after": os.getloadavg()[0],
            "emulator_in_c": "(process data in C)" in emulator_log,
            "steal_ms": {cpu: steal_after.get(cpu, 0) - steal_before.get(cpu, 0) for cpu in cpus},
            "emulator_log_tail": emulator_log.splitlines()[-3:]}


def _us(stats: dict[str, float | None] | None, key: str) -> str:
    value = (stats or {}).get(key)
    return "-" if value is None else f"{value / 1000:.0f} µs"


def table_row(result: dict[str, Any]) -> str:
    """One row of BENCHMARKS.md's table."""
    misses = result["deadline_misses"] or 0
    task = f"{result['cycles'] or 0:,} cycles, {misses} deadline miss{'' if misses == 1 else 'es'}"
    if (result["latency_ns"] or {}).get("p50") is not None:
        task += (f"; release latency p50 {_us(result['latency_ns'], 'p50')}, p99 {_us(result['latency_ns'], 'p99')}, "
                 f"max {_us(result['latency_ns'], 'max')}; exec p50 {_us(result['exec_ns'], 'p50')}")
    cycle = re.search(r"at cycle \d+", result["ended"])
    why = re.search(r"exchange \d+ on \S+: (.*?)(?:: a slave lost|$)", result["ended"])
    ended = "its duration" if result["exit_code"] == 0 else \
        f"{cycle.group(0) if cycle else '?'}: `{why.group(1) if why else result['ended'][-120:]}`"
    cyclic = (f"{result['cyclictest_samples']:,}, max {result['cyclictest_max_us']} µs, "
              f"{result['cyclictest_over_period']} over the period" if result["cyclictest_samples"] else "-")
    steal = ", ".join(f"CPU {cpu} {ms:.0f} ms" for cpu, ms in (result.get("steal_ms") or {}).items())
    started = f" ({result['started']})" if result.get("started") else ""
    lost = "-" if "lost_frames_max" not in result else \
        (f"{result['lost_frames_max']} ({result['blind_ms']:g} ms): {result['lost_frames'] or 0} lost, at most "
         f"{result['lost_in_a_row_max'] or 0} in a row")
    return (f"| {result['period_us']} µs{started} | {task} | {lost} | {ended} | {cyclic} | "
            f"{result['load_before']:.1f} / {result['load_after']:.1f}{'; steal ' + steal if steal else ''} |")


def print_rows(results: list[dict[str, Any]]) -> None:
    print("\n| period | rtloop: cycles, misses, latency | lost_frames_max (blind at most): lost frames | how the run "
          "ended | cyclictest beside it: samples, max, over the period | load average before / after; steal in the "
          "run |\n|---|---|---|---|---|---|")
    for result in results:
        print(table_row(result))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--drives", type=int, default=6)
    parser.add_argument("--periods-us", default="1000,250")
    parser.add_argument("--duration-s", type=float, default=10.0)
    parser.add_argument("--lost-frames-ms", default="10,90",
                        help="for each: lost_frames_max so that the drives go at most this long without their frame")
    parser.add_argument("--cpu", type=int, default=0, help="the task's and cyclictest's CPU")
    parser.add_argument("--emulator-cpu", type=int, default=1)
    parser.add_argument("--json", help="write the results here")
    parser.add_argument("--rows-from", metavar="JSON", help="only print the table rows of an earlier --json")
    args = parser.parse_args()
    if args.rows_from:
        print_rows(json.loads(Path(args.rows_from).read_text())["runs"])
        return 0
    problem = veth_problem()
    if problem:
        print(f"bench_ethercat_drives: {problem}", file=sys.stderr)
        return 2
    if compiled.devio() is None:
        print(f"bench_ethercat_drives: the emulator's compiled path is not here ({compiled.why_python()}): "
              "the runs would measure the Python emulator", file=sys.stderr)
        return 2
    answers = {"compiled": answer_time_us(True, 400), "python": answer_time_us(False, 40, batches=3)}
    print(f"emulated drives' answer to one cycle frame (six drives, LRW + FRMW, in process): compiled best "
          f"{answers['compiled']['best_us']:.1f} µs (median batch {answers['compiled']['median_us']:.1f}), Python "
          f"best {answers['python']['best_us']:.0f} µs (median batch {answers['python']['median_us']:.0f})",
          flush=True)
    results = []
    with tempfile.TemporaryDirectory(prefix="ecat-drives-") as folder:
        trips = {answerer: round_trip_us(answerer, args, Path(folder)) for answerer in ("echo", "emulator", "echo2")}
        for answerer, trip in trips.items():
            print(f"cycle frame round trip through the {answerer.rstrip('2')}: {trip['answered']} of {trip['sent']} "
                  f"answered, min {trip['min_us']:.0f} µs, p50 {trip['p50_us']:.0f}, p99 {trip['p99_us']:.0f}, "
                  f"max {trip['max_us']:.0f}", flush=True)
        budgets = [float(b) for b in args.lost_frames_ms.split(",")]
        for period_us, budget_ms in ((int(p), b) for p in args.periods_us.split(",") for b in budgets):
            try:
                results.append(one_period(period_us, budget_ms, args, Path(folder)))
            except VethError as error:
                print(f"bench_ethercat_drives: {error}", file=sys.stderr)
                return 3
            print(json.dumps(results[-1], indent=1), flush=True)
    print_rows(results)
    if args.json:
        Path(args.json).write_text(json.dumps({"answer_time": answers, "round_trip": trips, "runs": results},
                                              indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
