"""What a running app makes the disk do, and where the disk's answers land: a no-op task at 1 kHz.

A disk's completion interrupt and its block softirq run on the CPU the interrupt is bound to,
before any task there whatever its priority (on the project's VM: IRQ 36, ``virtio1-req.0``, on
CPU 1 only, and the kernel refuses to move it). This counts, for one run of one no-op task
(SCHED_FIFO 80 on ``--cpu``, 1 kHz, ``--seconds`` long), the block requests sent to the disks with
the kernel's ``block`` events (a tracing instance of its own, every CPU): who issued them (this
process, i.e. rtloop's supervisor; the kernel's writeback and journal threads; other programs),
the cache flushes among them, and how many completed on the task's CPU; and the device interrupts
that CPU took (/proc/interrupts). Variants, in a rotating order each round:

- ``synced``: summary.json synced (fsync) at every 2 s rewrite, as rtloop did before issue 33
  (put back for the comparison);
- ``now``:    rtloop as it is (the summary synced at the start and the end only, on ext4);
- ``tmpfs``:  as now, the run's folder in /dev/shm (nothing for the disk);
- ``idle``:   no run, the same seconds: what the machine's other programs make the disk do.

The supervisor's own requests are the figure to compare: the others are the machine's (the kernel's
writeback of everyone's files, other programs), and ``idle`` says how many.

Usage (as root)::

    python benchmarks/bench_disk_writes.py                          # 2 rounds x 20 s per variant
    python benchmarks/bench_disk_writes.py --rounds 3 --json disk.json
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (
    NoOp,
    add_output_options,
    closing_sections,
    machine_facts,
    markdown_table,
    parse_options,
    print_and_save,
    result_head,
    summary_synced_every_rewrite,
)
from bench_latency import interrupts_on

import rtloop
from rtloop.app.builder import App
from rtloop.linux import trace

VARIANTS = ("synced", "now", "tmpfs", "idle")
EVENTS = ("block/block_rq_issue", "block/block_rq_complete")
ISSUERS = ("rtloop supervisor", "kernel writeback and journal", "other programs")


class BlockTrace:
    """A tracing instance of this process's own with the block layer's events on every CPU."""

    def __init__(self) -> None:
        self.mounted: Path | None = None
        tracefs = trace.find_tracefs()
        if tracefs is None:
            tracefs = self.mounted = trace.mount_tracefs()  # OSError without root
        self.root = tracefs / "instances" / f"rtloop-disk-{os.getpid()}"
        self.root.mkdir()
        (self.root / "buffer_size_kb").write_text("8192")
        (self.root / "trace_clock").write_text("mono")
        for event in EVENTS:
            (self.root / "events" / event / "enable").write_text("1")

    def record(self, block: Any) -> dict[int, list[trace.Event]]:
        """Run ``block`` with the events on; what each CPU recorded."""
        (self.root / "trace").write_text("")
        (self.root / "tracing_on").write_text("1")
        try:
            block()
        finally:
            (self.root / "tracing_on").write_text("0")
        events: dict[int, list[trace.Event]] = {}
        for folder in sorted((self.root / "per_cpu").iterdir()):
            text = (folder / "trace").read_text(errors="replace")
            events[int(folder.name[3:])] = [e for line in text.splitlines() if (e := trace.parse(line)) is not None]
        return events

    def close(self) -> None:
        with contextlib.suppress(OSError):
            (self.root / "tracing_on").write_text("0")
        with contextlib.suppress(OSError):
            self.root.rmdir()
        if self.mounted is not None:
            trace.unmount(self.mounted)


def issuer(event: trace.Event) -> str:
    if event.context_pid == os.getpid():
        return ISSUERS[0]
    if event.context_comm.startswith(("kworker", "jbd2")):
        return ISSUERS[1]
    return ISSUERS[2]


def count(events: dict[int, list[trace.Event]], cpu: int, seconds: float) -> dict[str, float]:
    """Requests per second: issued, by whom; cache flushes; completed on ``cpu``, by whose request."""
    counts: collections.Counter[str] = collections.Counter()
    issued_by: dict[str, str] = {}
    for event in sorted((e for per_cpu in events.values() for e in per_cpu), key=lambda e: e.at_ns):
        if event.kind == "disk_issue":
            who = issuer(event)
            counts[f"issued: {who}"] += 1
            counts["cache flushes (anyone's)"] += "F" in event.flags
            issued_by[event.who] = who
    for event in events.get(cpu, []):
        if event.kind == "disk_done":
            counts[f"completed on CPU {cpu}: {issued_by.get(event.who, 'not seen issued')}"] += 1
    return {name: round(value / seconds, 2) for name, value in sorted(counts.items())}


def one_run(args: argparse.Namespace, variant: str, work: Path) -> None:
    if variant == "idle":
        time.sleep(args.seconds)
        return
    out = Path(tempfile.mkdtemp(prefix="run-", dir="/dev/shm" if variant == "tmpfs" else work))
    try:
        with summary_synced_every_rewrite(variant == "synced"):
            app = App("bench_disk_writes")
            app.add_task("noop", NoOp(), period_ns=args.period_us * 1000, priority=args.priority, cpu=args.cpu)
            rtloop.run(app, args.seconds, out / "run")
    finally:
        shutil.rmtree(out, ignore_errors=True)


def run(args: argparse.Namespace) -> dict[str, Any]:
    work = Path(tempfile.mkdtemp(prefix="rtloop-bench-disk-"))  # on the disk /tmp is on
    rows: dict[str, list[dict[str, float]]] = {variant: [] for variant in args.variants}
    facts, started = machine_facts(), time.monotonic()
    tracer = BlockTrace()
    try:
        for index in range(args.rounds):
            shift = index % len(args.variants)
            for variant in args.variants[shift:] + args.variants[:shift]:
                before, started = interrupts_on(args.cpu), time.monotonic()
                events = tracer.record(lambda variant=variant: one_run(args, variant, work))
                seconds = time.monotonic() - started
                figures = count(events, args.cpu, seconds)
                for name, value in interrupts_on(args.cpu).items():
                    if not name.split()[0].isdigit():
                        continue  # the timer's and the scheduler's own: every contender's alike
                    if (per_s := round((value - before.get(name, 0)) / seconds, 2)) > 0:
                        figures[f"IRQ {name} on CPU {args.cpu}"] = per_s
                figures["load average"] = float(Path("/proc/loadavg").read_text().split()[0])
                rows[variant].append(figures)
                if args.verbose:
                    print(f"round {index + 1}: {variant}: {figures}", file=sys.stderr, flush=True)
    finally:
        tracer.close()
        shutil.rmtree(work, ignore_errors=True)
    return {**result_head("disk_writes", args, facts, started), "runs": rows}


def report_markdown(result: dict[str, Any]) -> str:
    settings, runs = result["settings"], result["runs"]
    names = sorted({name for figures in runs.values() for run in figures for name in run if name != "load average"},
                   key=lambda name: (not name.startswith("issued: rtloop"), not name.startswith("issued"), name))
    header = ["per second", *(f"{variant} (each round)" for variant in runs)]
    rows = [[name, *(" / ".join(f"{run.get(name, 0):g}" for run in figures) for figures in runs.values())]
            for name in names]
    rows.append(["load average (1 min, at the end)",
                 *(" / ".join(f"{run['load average']:g}" for run in figures) for figures in runs.values())])
    return "\n\n".join([
        f"### Block requests and device interrupts per second, {settings['rounds']} rounds × {settings['seconds']} s "
        f"per variant, a no-op task at {settings['period_us']} µs on CPU {settings['cpu']}",
        markdown_table(header, rows),
        *closing_sections(result),
    ])


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=2, help="rounds of one run per variant (default 2)")
    parser.add_argument("--seconds", type=float, default=20.0, help="seconds per run (default 20)")
    parser.add_argument("--variants", type=lambda text: tuple(text.split(",")), default=VARIANTS,
                        help=f"comma-separated, of {','.join(VARIANTS)} (default all)")
    parser.add_argument("--period-us", type=int, default=1000)
    parser.add_argument("--priority", type=int, default=80)
    parser.add_argument("--cpu", type=int, default=1)
    parser.add_argument("-v", "--verbose", action="store_true", help="each run's figures on stderr")
    add_output_options(parser)
    args = parse_options(parser, argv)
    unknown = [variant for variant in args.variants if variant not in VARIANTS]
    if unknown:
        parser.error(f"--variants: {', '.join(unknown)} not among {', '.join(VARIANTS)}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if os.geteuid() != 0 or not trace.availability()[0]:
        print(f"needs root and tracefs: {trace.availability()[1] or 'run it as root'}", file=sys.stderr)
        return 2
    result = run(args)
    return print_and_save(report_markdown(result), result, args.json)


if __name__ == "__main__":
    raise SystemExit(main())
