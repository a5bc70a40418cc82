"""Where a wake-up's latency goes, rtloop beside cyclictest: the kernel's own events on the measured CPU.

bench_latency.py gives the two p99s; this says what makes the difference. It alternates blocks of
an rtloop no-op task and of cyclictest (same CPU, priority and period) with the kernel's scheduler,
hrtimer, IRQ and softirq events and ``clock_nanosleep``'s return recorded on that CPU only (a
tracing instance of its own, ``trace_clock mono``: the tasks' clock), and splits every wake-up:

- ``timer``:  the sleep's expiry → the hrtimer firing (the VM's timer delivery, IRQs off);
- ``to run``: the hrtimer firing → the switch to the thread (what the CPU was busy with);
- ``exit``:   the switch → ``clock_nanosleep`` returning to user space;
- ``user``:   → the contender's own stamp (rtloop's ``start_ns``; cyclictest's expiry + its sample).

The lines are read by rtloop's own parser (``rtloop.linux.trace``, what ``rtloop run --trace-misses``
uses), with its one rule for a kernel that leaves the switch out of idle untraced (this VM's 6.18: on
a quiet machine nearly every wake-up comes from idle): the thread's first own event is its switch-in,
so ``exit`` then reads 0 and ``to run`` holds it.

For the slowest 1 % of each contender's wake-ups it sums what held the CPU between the expiry
and the switch: threads (the benchmark's own process, i.e. rtloop's supervisor, is named
``rtloop supervisor``), IRQ handlers and softirqs. Needs root and tracefs (mounted for the run
when it is not). The events cost a little: compare the contenders with each other, not with
bench_latency.py's figures.

Usage (as root, cyclictest installed)::

    python benchmarks/bench_wakeup_trace.py                      # 2 rounds x 5 s at 1000 µs
    python benchmarks/bench_wakeup_trace.py --rounds 4 --block-s 10 --json wakeups.json
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import functools
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

import rtloop

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import NoOp, facts_markdown, load_timing_csv, machine_facts, markdown_table, write_json

from rtloop.app.builder import App
from rtloop.linux import trace

EVENTS = ("sched/sched_switch", "timer/hrtimer_start", "timer/hrtimer_expire_entry", "raw_syscalls/sys_exit",
          "irq/irq_handler_entry", "irq/irq_handler_exit", "irq/softirq_entry", "irq/softirq_exit")
CLOCK_NANOSLEEP_NR = {"x86_64": 230, "aarch64": 115, "armv7l": 265}.get(platform.machine())
PARTS = ("timer", "to run", "exit", "user", "total")


class Instance:
    """A tracing instance of this process's own on one CPU (the machine's tracing left alone)."""

    def __init__(self, cpu: int) -> None:
        self.mounted = None
        tracefs = trace.find_tracefs()
        if tracefs is None:
            tracefs = self.mounted = trace.mount_tracefs()  # OSError without root
        self.root = tracefs / "instances" / f"rtloop-wakeups-{os.getpid()}"
        self.root.mkdir()
        self.write("trace_clock", "mono")
        self.write("buffer_size_kb", "30000")
        self.write("tracing_cpumask", f"{1 << cpu:x}")
        for event in EVENTS:
            with contextlib.suppress(OSError):
                self.write(f"events/{event}/enable", "1")
        if CLOCK_NANOSLEEP_NR is not None:  # only the sleep's return: every other syscall would flood the buffer
            self.write("events/raw_syscalls/sys_exit/filter", f"id == {CLOCK_NANOSLEEP_NR}")

    def write(self, name: str, value: str) -> None:
        (self.root / name).write_text(value)

    def record(self, block: Any) -> str:
        self.write("trace", "")
        self.write("tracing_on", "1")
        try:
            block()
        finally:
            self.write("tracing_on", "0")
        return (self.root / "trace").read_text(errors="replace")

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.write("tracing_on", "0")
            self.root.rmdir()
        if self.mounted is not None:
            trace.unmount(self.mounted)


def parse(text: str) -> list[trace.Event]:
    """The trace's lines as rtloop's own parser reads them (``rtloop run --trace-misses`` uses it too)."""
    return [event for line in text.splitlines() if (event := trace.parse(line)) is not None]


def threads_switched_in(events: list[trace.Event]) -> set[int]:
    """The threads that ran on the CPU: switched in or out, the switches the kernel left untraced put back."""
    return {pid for event in trace.with_untraced_switches(events) if event.kind == "switch"
            for pid in (trace.pid_of(event.who), trace.pid_of(event.prev)) if pid > 0}


def wakeups(events: list[trace.Event], thread: int,
            own_pids: set[int]) -> tuple[np.ndarray, list[collections.Counter[str]]]:
    """(expiry, fire, switch-in, sleep's return) per wake-up of ``thread`` from an absolute sleep, and what
    held the CPU between its expiry and its switch-in. A switch-in the kernel left untraced (the switch
    out of idle, on this VM's 6.18) is put back by ``trace.with_untraced_switches``: the thread's first own
    event then bounds it, and its ``exit`` part reads 0."""
    rows, held = [], []
    timer, running = "", ""
    expiry = fire = switched = since = 0
    blame: collections.Counter[str] = collections.Counter()
    opened: dict[str, tuple[int, str]] = {}
    for event in trace.with_untraced_switches(events):
        kind, at_ns = event.kind, event.at_ns
        if kind in ("irq", "softirq"):
            opened[kind] = (at_ns, event.who)
        elif kind in ("irq_end", "softirq_end") and kind[:-4] in opened:
            start_ns, name = opened.pop(kind[:-4])
            if expiry and not switched and at_ns > expiry:
                blame[name] += at_ns - max(start_ns, expiry)
        elif kind == "sleep_armed" and event.context_pid == thread:
            timer, expiry, fire, switched = event.who, event.expires_ns, 0, 0
            blame = collections.Counter()
        elif kind == "sleep_fired" and expiry and event.who == timer:
            fire = at_ns
        elif kind == "switch":
            if expiry and not switched and running not in ("", "swapper") and at_ns > expiry:
                blame[running] += at_ns - max(since, expiry)
            next_pid = trace.pid_of(event.who)
            running = "rtloop supervisor" if next_pid in own_pids else "swapper" if next_pid == 0 else event.who
            since = at_ns
            if next_pid == thread and expiry and fire and not switched:
                switched = at_ns
        elif kind == "syscall_exit" and event.context_pid == thread and switched:
            rows.append((expiry, fire, switched, at_ns))
            held.append(blame)
            expiry = switched = 0
    return np.array(rows, dtype=np.int64).reshape(-1, 4), held


def run_rtloop(args: argparse.Namespace, out: Path) -> None:
    app = App("bench_wakeups")
    app.add_task("noop", NoOp(), period_ns=args.period_us * 1000, priority=args.priority, cpu=args.cpu)
    rtloop.run(app, args.block_s, out, trim=0)


def run_cyclictest(args: argparse.Namespace, tids: set[int]) -> list[int]:
    """cyclictest's samples (ns); ``tids`` gets its threads (another cyclictest may run on the CPU too)."""
    loops = max(1, round(args.block_s * 1e6 / args.period_us))
    other = sorted(os.sched_getaffinity(0) - {args.cpu}) or [args.cpu]
    command = ["cyclictest", "-m", "-p", str(args.priority), "-a", str(args.cpu), "-t", "1", "-i",
               str(args.period_us), "-d", "0", "-l", str(loops), "-q", "-v", "-N", f"--mainaffinity={other[0]}"]
    with subprocess.Popen(command, stdout=subprocess.PIPE, text=True) as process:
        while process.poll() is None and len(tids) < 2:  # its measuring thread starts at once
            with contextlib.suppress(OSError):
                tids.update(int(tid) for tid in os.listdir(f"/proc/{process.pid}/task"))
        stdout, _ = process.communicate()
    if process.returncode:
        raise subprocess.CalledProcessError(process.returncode, command)
    return [int(m[1]) for line in stdout.splitlines() if (m := re.match(r"^\s*0:\s*\d+:\s*(\d+)\s*$", line))]


def cyclictest_into(args: argparse.Namespace, samples: list[int], tids: set[int]) -> None:
    samples.extend(run_cyclictest(args, tids))


def align(rows: np.ndarray, held: list[Any], samples: np.ndarray) -> tuple[np.ndarray, list[Any], np.ndarray]:
    """cyclictest's samples are its wake-ups in order, without the first (and any the trace lost at its
    ends): the offset at which each sample's stamp (expiry + sample) falls closest after the sleep's return."""
    best: tuple[float, int, int] | None = None
    for shift in range(-3, 4):
        rows_from, samples_from = max(0, shift), max(0, -shift)
        count = min(len(rows) - rows_from, len(samples) - samples_from)
        if count <= 0:
            continue
        user = rows[rows_from:rows_from + count, 0] + samples[samples_from:samples_from + count] \
            - rows[rows_from:rows_from + count, 3]
        spread = float(np.percentile(np.abs(user), 99))
        if best is None or spread < best[0]:
            best = (spread, rows_from, samples_from)
    if best is None:
        return rows[:0], [], np.empty(0, dtype=np.int64)
    _, rows_from, samples_from = best
    count = min(len(rows) - rows_from, len(samples) - samples_from)
    kept = rows[rows_from:rows_from + count]
    return kept, held[rows_from:rows_from + count], kept[:, 0] + samples[samples_from:samples_from + count]


def run(args: argparse.Namespace) -> dict[str, Any]:
    parts: dict[str, list[np.ndarray]] = {"rtloop": [], "cyclictest": []}
    blamed: dict[str, list[tuple[float, collections.Counter[str]]]] = {"rtloop": [], "cyclictest": []}
    work = Path(tempfile.mkdtemp(prefix="rtloop-bench-wakeups-"))
    instance = Instance(args.cpu)
    facts = machine_facts()
    try:
        for index in range(args.rounds):
            for contender in (("rtloop", "cyclictest") if index % 2 == 0 else ("cyclictest", "rtloop")):
                if contender == "rtloop":
                    out = work / f"r{index}"
                    events = parse(instance.record(lambda out=out: run_rtloop(args, out)))
                    stamps = dict(load_timing_csv(out / "timing.csv")["noop"][:, 1:3].tolist())
                    # the task's thread: the one whose sleeps end at its releases (another app's may share the CPU)
                    rows, held = max((wakeups(events, tid, {os.getpid()}) for tid in threads_switched_in(events)),
                                     key=lambda found: sum(int(row[0]) in stamps for row in found[0]))
                    keep = [k for k, row in enumerate(rows) if int(row[0]) in stamps]
                    rows, held = rows[keep], [held[k] for k in keep]
                    user_end = np.array([stamps[int(row[0])] for row in rows], dtype=np.int64)
                else:
                    samples: list[int] = []
                    tids: set[int] = set()
                    events = parse(instance.record(functools.partial(cyclictest_into, args, samples, tids)))
                    rows, held = max((wakeups(events, tid, set()) for tid in tids & threads_switched_in(events)),
                                     key=lambda found: len(found[0]), default=(np.empty((0, 4), dtype=np.int64), []))
                    rows, held, user_end = align(rows, held, np.array(samples, dtype=np.int64))
                expiry, fire, switched, returned = rows.T
                split = np.column_stack([fire - expiry, switched - fire, returned - switched, user_end - returned,
                                         user_end - expiry]) / 1000
                parts[contender].append(split)
                blamed[contender] += list(zip(split[:, 4].tolist(), held, strict=True))
    finally:
        instance.close()
        facts["loadavg_at_end"] = Path("/proc/loadavg").read_text().split()[:3]
        shutil.rmtree(work, ignore_errors=True)
    result: dict[str, Any] = {"benchmark": "wakeup_trace", "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
                              "settings": vars(args), "machine": facts, "contenders": {}}
    for contender, blocks in parts.items():
        split = np.concatenate(blocks) if blocks else np.empty((0, 5))
        slow_from = float(np.percentile(split[:, 4], 99)) if len(split) else 0.0
        blame: collections.Counter[str] = collections.Counter()
        slow = [held for total, held in blamed[contender] if total >= slow_from]
        for held in slow:
            blame.update(held)
        result["contenders"][contender] = {
            "wakeups": len(split),
            "us": {part: {"p50": float(np.median(split[:, k])), "p99": float(np.percentile(split[:, k], 99))}
                   for k, part in enumerate(PARTS)} if len(split) else {},
            "slowest_1pct_from_us": slow_from,
            "slowest_1pct_held_by_us": {name: round(ns / 1000, 1) for name, ns in blame.most_common(10)},
            "slowest_1pct_count": len(slow),
        }
    return result


def report_markdown(result: dict[str, Any]) -> str:
    settings, contenders = result["settings"], result["contenders"]
    rows = [[name, entry["wakeups"], *(f"{entry['us'][part]['p50']:.1f} / {entry['us'][part]['p99']:.1f}"
                                       for part in PARTS)]
            for name, entry in contenders.items() if entry["us"]]
    blame_rows = [[name, f"{entry['slowest_1pct_count']} from {entry['slowest_1pct_from_us']:.1f} µs",
                   ", ".join(f"{who} {us:.0f}" for who, us in entry["slowest_1pct_held_by_us"].items()) or "nothing"]
                  for name, entry in contenders.items()]
    return "\n\n".join([
        f"### A wake-up's latency, part by part (µs, p50 / p99), {settings['rounds']} rounds × {settings['block_s']} s "
        f"at {settings['period_us']} µs, priority {settings['priority']}, CPU {settings['cpu']}",
        markdown_table(["contender", "wake-ups", *PARTS], rows),
        "### What held the CPU between the expiry and the switch, summed over the slowest 1 % (µs)",
        markdown_table(["contender", "wake-ups", "held by"], blame_rows),
        "### Machine",
        facts_markdown(result["machine"]),
    ])


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=2, help="rounds of one block each (default 2)")
    parser.add_argument("--block-s", type=float, default=5.0, help="seconds per block (default 5)")
    parser.add_argument("--period-us", type=int, default=1000)
    parser.add_argument("--priority", type=int, default=80)
    parser.add_argument("--cpu", type=int, default=1)
    parser.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if shutil.which("cyclictest") is None:
        print("cyclictest not found (Debian: apt-get install rt-tests)", file=sys.stderr)
        return 2
    if os.geteuid() != 0 or not trace.availability()[0]:
        print(f"needs root and tracefs: {trace.availability()[1] or 'run it as root'}", file=sys.stderr)
        return 2
    result = run(args)
    print(report_markdown(result))
    if args.json:
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
