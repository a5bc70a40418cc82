"""Wake-up latency side by side: an rtloop no-op task, cyclictest, and a naive Python loop.

One run alternates blocks of the three contenders, so they share the same machine
state (other load, thermal, hypervisor noise). Each round runs, in a rotating order:

- ``rtloop``     an App with one no-op task (SCHED_FIFO, pinned, absolute clock_nanosleep);
                 latency = start − release from its ``timing.csv``.
- ``cyclictest`` ``cyclictest -m -p PRIO -a CPU -t 1 -i PERIOD -d 0 -l N -q -v -N``: the
                 ``-v -N`` output gives every sample in nanoseconds (no histogram binning).
- ``naive``      a SCHED_OTHER Python process on the same CPU doing
                 ``time.sleep(period - elapsed)``; latency = actual wake − intended wake
                 on its own relative timeline, plus its drift from the ideal absolute
                 timeline first_start + k·P (it drifts: every late wake-up accumulates).

and then the fast blocks at ``--fast-period-us`` (default 100 µs = 10 kHz), rtloop vs
cyclictest, for the miss rate (miss = a wake-up later than one period).

Every block's own p99 is printed too, each rtloop block beside the cyclictest block of the
same round (a block hit by something else on the machine shows there, not only in the pooled
p99), and the real-time threads of other programs that may run on the measured CPU, seen
before each block (another app's task, a test's FIFO hog: what makes a "quiet" run not quiet).

It also measures the framework's own per-cycle cost: the median ``exec_ns`` (end − start)
of the no-op task in the real runs, and, in-process, one whole iteration of the task's loop
on the hot path a task uses (C when built) without its sleep (read inputs, the tick, step,
publish, the timing record and the status words: everything but the sleep system call).

Usage (as root, cyclictest installed)::

    python benchmarks/bench_latency.py --quick             # < 1 minute
    python benchmarks/bench_latency.py --rounds 4 --block-s 15 --json latency.json
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import rtloop

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (
    STAT_COLUMNS,
    NoOp,
    PmQos,
    facts_markdown,
    load_timing_csv,
    machine_facts,
    markdown_table,
    stats_us,
    summary_synced_every_rewrite,
    trim,
    write_json,
)

from rtloop.app.builder import App
from rtloop.ipc.hotpath import hot_path
from rtloop.toolbox.bench import rt_neighbours

P99_RATIO_TARGET = 1.1
"""rtloop's p99 wake-up latency at most this many times cyclictest's in the same run (issue 33)."""

CYCLICTEST_SAMPLE = re.compile(r"^\s*0:\s*\d+:\s*(\d+)\s*$")


@dataclass
class Samples:
    """Everything one contender recorded at one period, over all its blocks."""

    contender: str
    period_us: int
    latency_ns: list[np.ndarray] = field(default_factory=list)
    exec_ns: list[np.ndarray] = field(default_factory=list)
    drift_ns_per_1k: list[float] = field(default_factory=list)
    drift_end_ns: list[float] = field(default_factory=list)
    skipped: int = 0
    deadline_misses: int = 0
    lost: int = 0
    blocks: int = 0
    block_p99_us: list[float] = field(default_factory=list)
    """Each block's own p99 wake-up latency, in run order (one per round)."""
    interrupts: dict[str, int] = field(default_factory=dict)
    """Interrupts the measured CPU took during this contender's blocks, per /proc/interrupts line."""
    seconds: float = 0.0

    def latency(self) -> np.ndarray:
        return np.concatenate(self.latency_ns) if self.latency_ns else np.empty(0)

    def executions(self) -> np.ndarray:
        return np.concatenate(self.exec_ns) if self.exec_ns else np.empty(0)


# --- the three contenders ----------------------------------------------------------------------
def run_rtloop_block(args: argparse.Namespace, period_us: int, block_s: float, out: Path, into: Samples) -> None:
    app = App("bench_latency")
    app.add_task("noop", NoOp(), period_ns=period_us * 1000, priority=args.priority, cpu=args.cpu)
    summary = rtloop.run(app, block_s, out, trim=args.trim)
    task = summary.tasks["noop"]
    if not task.rt:
        raise SystemExit(f"rtloop task did not run real-time: {task.rt_reason}")
    records = load_timing_csv(out / "timing.csv")["noop"]
    cycles, release, _, end = records.T
    period_ns = period_us * 1000
    into.skipped += int(np.sum(np.diff(cycles) - 1)) if len(cycles) > 1 else 0
    into.deadline_misses += int(np.count_nonzero(end > release + period_ns))
    core = trim(records, args.trim)
    into.latency_ns.append(core[:, 2] - core[:, 1])
    into.exec_ns.append(core[:, 3] - core[:, 2])
    into.block_p99_us.append(block_p99_us(into.latency_ns[-1]))
    into.blocks += 1


def run_cyclictest_block(args: argparse.Namespace, period_us: int, block_s: float, into: Samples) -> None:
    loops = max(1, round(block_s * 1e6 / period_us))
    other_cpus = sorted(os.sched_getaffinity(0) - {args.cpu}) or [args.cpu]
    command = [
        "cyclictest", "-m", "-p", str(args.priority), "-a", str(args.cpu), "-t", "1",
        "-i", str(period_us), "-d", "0", "-l", str(loops), "-q", "-v", "-N",
        f"--mainaffinity={other_cpus[0]}",
    ]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, check=True)
    values = [int(m.group(1)) for line in result.stdout.splitlines() if (m := CYCLICTEST_SAMPLE.match(line))]
    into.lost += loops - len(values)
    everything = np.array(values, dtype=np.int64)
    # cyclictest never reports a release it slept through: after a wake-up at release + L
    # it moves on to the first release after "now", so ceil(L / P) − 1 releases are skipped
    # silently. Count them as rtloop counts its own skipped releases.
    period_ns = period_us * 1000
    into.skipped += int(np.sum(np.maximum(0, -(-everything // period_ns) - 1)))
    latency = trim(everything, args.trim)
    into.latency_ns.append(latency)
    into.block_p99_us.append(block_p99_us(latency))
    into.blocks += 1


def run_naive_block(args: argparse.Namespace, period_us: int, block_s: float, out: Path, into: Samples) -> None:
    cycles = max(1, round(block_s * 1e6 / period_us))
    result_file = out.with_suffix(".npz")
    command = [sys.executable, __file__, "--naive-child", "--period-us", str(period_us),
               "--cycles", str(cycles), "--cpu", str(args.cpu), "--child-out", str(result_file)]  # fmt: skip
    subprocess.run(command, check=True)
    with np.load(result_file) as data:
        intended, woke, first_top = data["intended_ns"], data["woke_ns"], int(data["first_top_ns"])
    period_ns = period_us * 1000
    ideal = first_top + (np.arange(len(woke)) + 1) * period_ns  # where an absolute timeline would wake
    drift = woke - ideal
    into.latency_ns.append(trim(woke - intended, args.trim))
    into.block_p99_us.append(block_p99_us(into.latency_ns[-1]))
    into.drift_end_ns.append(float(drift[-1]))
    into.drift_ns_per_1k.append(float(np.polyfit(np.arange(len(drift)), drift, 1)[0]) * 1000)
    into.blocks += 1


def block_p99_us(latency_ns: np.ndarray) -> float:
    return float(np.percentile(latency_ns, 99)) / 1000 if len(latency_ns) else float("nan")


def interrupts_on(cpu: int) -> dict[str, int]:
    """The interrupts ``cpu`` has taken so far, per line of /proc/interrupts ("36 virtio1-req.0", "LOC Local timer")."""
    counts: dict[str, int] = {}
    try:
        lines = Path("/proc/interrupts").read_text().splitlines()
        column = lines[0].split().index(f"CPU{cpu}")
    except (OSError, ValueError, IndexError):
        return counts
    for line in lines[1:]:
        label, _, rest = line.partition(":")
        fields = rest.split()
        if len(fields) > column and fields[column].isdigit():
            name = " ".join(word for word in fields if not word.isdigit())
            counts[f"{label.strip()} {name.split()[-1] if label.strip().isdigit() else name}"] = int(fields[column])
    return counts


def other_realtime_threads(cpu: int) -> set[str]:
    """Real-time threads of other programs that may run on ``cpu`` now (a walk of /proc: between blocks)."""
    return set(rt_neighbours({cpu}))


def naive_child(period_us: int, cycles: int, cpu: int, out: str) -> None:
    """The loop users write instead of rtloop: relative sleep, SCHED_OTHER. Runs in its own process."""
    os.sched_setaffinity(0, {cpu})
    period_s = period_us / 1e6
    intended = [0] * cycles
    woke = [0] * cycles
    now = time.monotonic_ns
    first_top = now()
    for k in range(cycles):
        top = now()
        # step() would go here
        delay_s = period_s - (now() - top) / 1e9
        called = now()
        time.sleep(max(delay_s, 0.0))
        woke[k] = now()
        intended[k] = called + round(delay_s * 1e9)
    np.savez(out, intended_ns=np.array(intended), woke_ns=np.array(woke), first_top_ns=first_top)


# --- the framework's own cost, in-process ------------------------------------------------------
def measure_loop_iteration(cycles: int, cpu: int) -> np.ndarray:
    """Per-iteration cost of the task loop without its sleep, in ns (start_k+1 − start_k), on the hot path
    a task uses here (C when built, ``hotpath.hot_path()``).

    Uses the real cycle work, status block and timing ring (shared memory) through the seams that take
    the clock instead of sleeping (``begin_at``/``finish_at``, each given ``time.monotonic_ns()``); runs
    in this process, pinned to ``cpu``, so medians are meaningful even without SCHED_FIFO.
    """
    from rtloop.app.specs import TaskConfig
    from rtloop.ipc.hotpath import cycle_work
    from rtloop.ipc.ring import Int64Ring
    from rtloop.ipc.schema import task_segment_size
    from rtloop.ipc.segments import Segment, new_run_token
    from rtloop.ipc.status import CONTROL_WORDS, STATUS_WORDS, WordBlock
    from rtloop.ipc.wiring import TaskWiringPlan
    from rtloop.linux import rt
    from rtloop.runtime.taskrun import TaskRun

    token = new_run_token()
    control_segment = Segment.create("bench", os.getpid(), token, "control", CONTROL_WORDS * 8)
    task_segment = Segment.create("bench", os.getpid(), token, "task", task_segment_size(cycles + 8))
    previous = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(0, {cpu})
        control = WordBlock(control_segment, 0, CONTROL_WORDS)
        status = WordBlock(task_segment, 0, STATUS_WORDS)
        timing = Int64Ring.initialise(task_segment, cycles + 8, 4, STATUS_WORDS * 8)
        period_ns = 1_000_000
        task = TaskRun(TaskConfig("noop", period_ns), NoOp(), TaskWiringPlan(), control, status, timing)
        # The task's loop (runtime/task.py) with the clock read where begin() would wake up.
        cycle = cycle_work(task.tick, task.wiring, control, status, timing, period_ns, catch_up=False)
        t0_ns = rt.now_ns() + 10**15  # releases in the far future: never an overrun path
        cycle.start(t0_ns, t0_ns + cycles * period_ns, 0)
        job, tick, clock = task.job, task.tick, time.monotonic_ns
        while cycle.begin_at(clock()):
            job(tick.cycle)
            cycle.finish_at(clock())
        records = timing.drain()
        return np.diff(records[:, 2])
    finally:
        os.sched_setaffinity(0, previous)
        for segment in (control_segment, task_segment):
            segment.unlink()


# --- the run -------------------------------------------------------------------------------------
def run(args: argparse.Namespace) -> dict[str, Any]:
    slow, fast = args.period_us, args.fast_period_us
    results: dict[tuple[str, int], Samples] = {
        key: Samples(*key)
        for key in [("rtloop", slow), ("cyclictest", slow), ("naive", slow), ("rtloop", fast), ("cyclictest", fast)]
    }
    order = [("rtloop", slow), ("cyclictest", slow), ("naive", slow)]
    fast_order = [("rtloop", fast), ("cyclictest", fast)] if fast else []
    work = Path(tempfile.mkdtemp(prefix="rtloop-bench-latency-"))
    facts = machine_facts()
    others: set[str] = set()
    started = time.monotonic()
    try:
        with PmQos(not args.no_pm_qos) as qos, summary_synced_every_rewrite(args.summary_synced):
            facts["cpu_dma_latency_held_at_0us"] = qos.active
            for round_index in range(args.rounds):
                shift = round_index % len(order)
                plan = [(key, args.block_s) for key in order[shift:] + order[:shift]]
                plan += [(key, args.fast_block_s) for key in (fast_order[::-1] if round_index % 2 else fast_order)]
                for (contender, period_us), block_s in plan:
                    into = results[(contender, period_us)]
                    others |= other_realtime_threads(args.cpu)
                    interrupts_before, started_s = interrupts_on(args.cpu), time.monotonic()
                    out = work / f"r{round_index}-{contender}-{period_us}us"
                    if args.verbose:
                        print(f"round {round_index + 1}/{args.rounds}: {contender} @ {period_us} µs, {block_s} s",
                              file=sys.stderr, flush=True)
                    if contender == "rtloop":
                        run_rtloop_block(args, period_us, block_s, out, into)
                    elif contender == "cyclictest":
                        run_cyclictest_block(args, period_us, block_s, into)
                    else:
                        run_naive_block(args, period_us, block_s, out, into)
                    into.seconds += time.monotonic() - started_s
                    for name, count in interrupts_on(args.cpu).items():
                        into.interrupts[name] = into.interrupts.get(name, 0) + count - interrupts_before.get(name, 0)
        iteration_ns = measure_loop_iteration(args.loop_cycles, args.cpu)
    finally:
        facts["loadavg_at_end"] = Path("/proc/loadavg").read_text().split()[:3]
        facts[f"other_realtime_threads_on_cpu_{args.cpu}"] = sorted(others) or "none seen (looked before each block)"
        if args.keep:
            print(f"artifacts kept in {work}", file=sys.stderr)
        else:
            shutil.rmtree(work, ignore_errors=True)
    return summarise(args, results, iteration_ns, facts, time.monotonic() - started)


def summarise(
    args: argparse.Namespace, results: dict[tuple[str, int], Samples], iteration_ns: np.ndarray,
    facts: dict[str, Any], elapsed_s: float,
) -> dict[str, Any]:
    latency = {}
    for (contender, period_us), samples in results.items():
        if not samples.blocks:
            continue
        data = samples.latency()
        late = int(np.count_nonzero(data > period_us * 1000))
        latency[f"{contender}@{period_us}us"] = {
            "contender": contender,
            "period_us": period_us,
            "samples": int(data.size),
            "latency_us": stats_us(data),
            "late_wakeups": late,
            "miss_rate": late / data.size if data.size else float("nan"),
            "skipped_releases": samples.skipped,
            "missed_releases": late + samples.skipped,
            "missed_rate": (late + samples.skipped) / (data.size + samples.skipped) if data.size else float("nan"),
            "deadline_misses": samples.deadline_misses,
            "samples_lost": samples.lost,
            "drift_us_per_1k_cycles": float(np.mean(samples.drift_ns_per_1k)) / 1000 if samples.drift_ns_per_1k
            else (0.0 if contender != "cyclictest" else float("nan")),
            "drift_at_block_end_ms": float(np.mean(samples.drift_end_ns)) / 1e6 if samples.drift_end_ns else None,
            "exec_us": stats_us(samples.executions()) if samples.exec_ns else None,
            "block_p99_us": [round(v, 2) for v in samples.block_p99_us],
            "interrupts_per_s_on_cpu": {name: round(count / samples.seconds, 1)
                                        for name, count in sorted(samples.interrupts.items()) if count},
        }
    overhead = {
        "rtloop_exec_us": latency[f"rtloop@{args.period_us}us"]["exec_us"],
        "loop_iteration_us": stats_us(iteration_ns),
        "loop_iteration_hot_path": hot_path(),
    }
    return {
        "benchmark": "latency",
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "settings": {k: v for k, v in vars(args).items() if k not in ("naive_child", "child_out", "cycles", "json")},
        "machine": facts,
        "elapsed_s": round(elapsed_s, 1),
        "latency": latency,
        "overhead": overhead,
        "targets": targets(args, latency, overhead),
    }


def targets(args: argparse.Namespace, latency: dict[str, Any], overhead: dict[str, Any]) -> list[dict[str, Any]]:
    slow, fast = args.period_us, args.fast_period_us
    rt_p99 = latency[f"rtloop@{slow}us"]["latency_us"]["p99"]
    ct_p99 = latency[f"cyclictest@{slow}us"]["latency_us"]["p99"]
    checks = [
        {
            "target": f"rtloop p99 wake-up latency ≤ {P99_RATIO_TARGET} × cyclictest p99 (@{slow} µs)",
            "measured": f"{rt_p99:.2f} µs vs {ct_p99:.2f} µs (×{rt_p99 / ct_p99:.2f}, target ×{P99_RATIO_TARGET})",
            "met": bool(rt_p99 <= P99_RATIO_TARGET * ct_p99),
        },
        {
            "target": "no-op step exec_ns median ≤ 5 µs",
            "measured": f"{overhead['rtloop_exec_us']['p50']:.2f} µs (whole iteration excl. sleep: "
            f"{overhead['loop_iteration_us']['p50']:.2f} µs)",
            "met": bool(overhead["rtloop_exec_us"]["p50"] <= 5.0),
        },
    ]
    if fast:
        rt_fast, ct_fast = latency[f"rtloop@{fast}us"], latency[f"cyclictest@{fast}us"]
        checks.append({
            "target": f"miss rate @{fast} µs ≤ cyclictest's (late wake-ups + skipped releases, over all releases)",
            "measured": f"rtloop {rt_fast['missed_rate']:.2e} ({rt_fast['late_wakeups']} late + "
            f"{rt_fast['skipped_releases']} skipped) vs cyclictest {ct_fast['missed_rate']:.2e} "
            f"({ct_fast['late_wakeups']} late + {ct_fast['skipped_releases']} skipped)",
            "met": bool(rt_fast["missed_rate"] <= ct_fast["missed_rate"]),
        })
    return checks


def report_markdown(result: dict[str, Any]) -> str:
    latency = result["latency"]
    rows = [
        [key.split("@")[0], entry["period_us"], entry["samples"], *(entry["latency_us"][c] for c in STAT_COLUMNS),
         entry["drift_us_per_1k_cycles"]]
        for key, entry in latency.items()
    ]
    miss_rows = [
        [key.split("@")[0], entry["period_us"], entry["samples"], entry["late_wakeups"], f"{entry['miss_rate']:.2e}",
         f"{entry['missed_releases']} ({entry['missed_rate']:.2e})", entry["skipped_releases"],
         entry["deadline_misses"] if entry["contender"] == "rtloop" else "n/a"]
        for key, entry in latency.items() if entry["contender"] != "naive"
    ]
    overhead = result["overhead"]
    overhead_rows = [
        ["rtloop exec_ns of a no-op step (end − start, real runs)",
         *(overhead["rtloop_exec_us"][c] for c in STAT_COLUMNS)],
        [f"whole loop iteration excl. the sleep syscall (in-process, {overhead['loop_iteration_hot_path']} hot path)",
         *(overhead["loop_iteration_us"][c] for c in STAT_COLUMNS)],
    ]
    target_rows = [[t["target"], t["measured"], "met" if t["met"] else "**MISSED**"] for t in result["targets"]]
    busiest = sorted({name for entry in latency.values() for name in entry["interrupts_per_s_on_cpu"]},
                     key=lambda name: -max(e["interrupts_per_s_on_cpu"].get(name, 0) for e in latency.values()))[:6]
    interrupt_rows = [[key.split("@")[0], entry["period_us"], *(entry["interrupts_per_s_on_cpu"].get(name, 0)
                                                                for name in busiest)]
                      for key, entry in latency.items()]
    block_rows = []
    for period_us in sorted({entry["period_us"] for entry in latency.values()}, reverse=True):
        mine, theirs = latency.get(f"rtloop@{period_us}us"), latency.get(f"cyclictest@{period_us}us")
        if mine is None or theirs is None:
            continue
        for index, (p99_mine, p99_theirs) in enumerate(zip(mine["block_p99_us"], theirs["block_p99_us"], strict=False)):
            block_rows.append([period_us, index + 1, p99_mine, p99_theirs, f"×{p99_mine / p99_theirs:.2f}"])
    settings = result["settings"]
    return "\n\n".join([
        f"### Wake-up latency (µs), {settings['rounds']} rounds × blocks of {settings['block_s']} s "
        f"({settings['fast_block_s']} s at the fast period), priority {settings['priority']}, CPU {settings['cpu']}"
        + (", summary.json synced at every rewrite (--summary-synced)" if settings.get("summary_synced") else ""),
        markdown_table(["contender", "period_us", "samples", "min", "p50", "p99", "p99.9", "max", "drift_us_per_1k"],
                       rows),
        "### Misses (late wake-up = latency > period; missed releases = late wake-ups + releases skipped after "
        "a late cycle, rate over all releases)",
        markdown_table(["contender", "period_us", "samples", "late_wakeups", "miss_rate", "missed_releases",
                        "skipped_releases", "deadline_misses"], miss_rows),
        "### Framework overhead per cycle (µs)",
        markdown_table(["measure", "min", "p50", "p99", "p99.9", "max"], overhead_rows),
        "### p99 per block (µs): rtloop beside cyclictest in the same round",
        markdown_table(["period_us", "round", "rtloop p99", "cyclictest p99", "ratio"], block_rows),
        f"### Interrupts on CPU {settings['cpu']} per second during each contender's blocks (/proc/interrupts: "
        "a device's interrupts and their softirq work delay a wake-up there whatever its priority)",
        markdown_table(["contender", "period_us", *busiest], interrupt_rows),
        "### Targets",
        markdown_table(["target", "measured", "result"], target_rows),
        "### Machine",
        facts_markdown(result["machine"]),
    ])


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=4, help="rounds of alternating blocks (default 4)")
    parser.add_argument("--block-s", type=float, default=15.0, help="seconds per block at --period-us (default 15)")
    parser.add_argument("--fast-block-s", type=float, default=None, help="seconds per fast block (default: block-s)")
    parser.add_argument("--period-us", type=int, default=1000, help="period of the main comparison (default 1000)")
    parser.add_argument("--fast-period-us", type=int, default=100, help="period for the miss-rate comparison; 0: skip")
    parser.add_argument("--priority", type=int, default=80)
    parser.add_argument("--cpu", type=int, default=1)
    parser.add_argument("--trim", type=int, default=20, help="cycles dropped at each end of every block (default 20)")
    parser.add_argument("--loop-cycles", type=int, default=100_000, help="iterations of the in-process loop timing")
    parser.add_argument("--quick", action="store_true", help="2 rounds × 3 s blocks: under a minute")
    parser.add_argument("--no-pm-qos", action="store_true", help="do not hold /dev/cpu_dma_latency at 0 µs")
    parser.add_argument("--summary-synced", action="store_true",
                        help="sync summary.json at every rewrite, as rtloop did before issue 33 (only the first and "
                             "the final one since): the 'before' of a before/after comparison in one checkout")
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    parser.add_argument("--keep", action="store_true", help="keep the per-block run directories")
    parser.add_argument("-v", "--verbose", action="store_true", help="print progress to stderr")
    parser.add_argument("--naive-child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--cycles", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--child-out", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.quick:
        args.rounds, args.block_s, args.loop_cycles = 2, 3.0, 20_000
    if args.fast_block_s is None:
        args.fast_block_s = args.block_s
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.naive_child:
        naive_child(args.period_us, args.cycles, args.cpu, args.child_out)
        return 0
    if shutil.which("cyclictest") is None:
        print("cyclictest not found (Debian: apt-get install rt-tests)", file=sys.stderr)
        return 2
    result = run(args)
    print(report_markdown(result))
    if args.json:
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
