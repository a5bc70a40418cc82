"""``rtloop why RUN [--cycle N] [--task T]``: why a run's cycles were late, with the evidence.

Without ``--cycle``: the run's account of its misses (one line per task, kind and cause) and the
first misses. With it: everything known of that cycle — its own timing, the task's counters, steal
and IRQ time on its CPU, the threads and tasks that ran meanwhile — from ``summary.json``'s
``misses`` (the first ones are kept in full); a later miss is explained again from ``timing.csv``
alone (its own timing and the other tasks' records), and says so.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import stat
from pathlib import Path
from typing import Any

from rtloop.errors import AppError

HELP = "why a run's cycles were late: each miss's cause and the evidence for one cycle"
NEAR_NS = 1_000_000_000
"""Other tasks' records read from timing.csv around the cycle asked about."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", type=Path, metavar="RUN", help="a run directory (the --out of rtloop run)")
    parser.add_argument("--cycle", type=int, metavar="N", help="the cycle to explain")
    parser.add_argument("--task", metavar="T", help="the task (default: every task that has cycle N)")


SUMMARY_READ_MAX_BYTES = 1 << 20
"""A summary.json larger than this is not one rtloop wrote: it keeps it within SUMMARY_BOUND_BYTES
(record/summary.py, 64 KiB; not imported here: it loads numpy, which rtloop --help must not)."""
TIMING_LINE_MAX_CHARS = 4096
"""A timing.csv line longer than this is not one rtloop wrote (five integers): a garbled or planted file
(2 GB of NUL bytes are one line) is refused at that line rather than read into memory whole."""


def run(args: argparse.Namespace) -> int:
    summary = _summary(args.run_dir)
    if args.task is not None and args.task not in summary.get("tasks", {}):
        raise AppError(f"{args.run_dir}: no task {args.task!r} in this run (tasks: {', '.join(summary['tasks'])})")
    try:
        if args.cycle is None:
            print("\n".join(account(summary)))
            return 0
        print("\n".join(explain_cycle(args.run_dir, summary, args.cycle, args.task)))
    except (KeyError, TypeError, AttributeError, IndexError) as error:  # a value of another shape than rtloop's
        raise AppError(f"{args.run_dir / 'summary.json'}: not an rtloop summary rtloop why reads "
                       f"({type(error).__name__}: {error})") from error
    return 0


def _open_regular(path: Path, missing: str, mode: str = "rb") -> Any:
    """``path`` opened if it is a regular file: a FIFO waits for a writer and /dev/zero behind a link
    never ends, each an endless wait where a line naming the file was due."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # non-blocking: opening a FIFO waits for a writer
    except FileNotFoundError:
        raise AppError(missing) from None
    except OSError as error:
        raise AppError(f"{path}: cannot be read ({error.strerror})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise AppError(f"{path}: not a regular file, so not one rtloop wrote")
    if mode == "rb":
        return os.fdopen(fd, "rb")
    return os.fdopen(fd, "r", newline="", encoding="utf-8")


def _summary(run_dir: Path) -> dict[str, Any]:
    path = run_dir / "summary.json"
    with _open_regular(path, f"{run_dir}: not a run directory (no summary.json)") as file:
        data = file.read(SUMMARY_READ_MAX_BYTES + 1)
    if len(data) > SUMMARY_READ_MAX_BYTES:
        raise AppError(f"{path}: more than {SUMMARY_READ_MAX_BYTES >> 10} KiB, not a summary rtloop wrote")
    try:
        summary = json.loads(data.decode("utf-8"))
    except ValueError as error:
        raise AppError(f"{path}: cannot be read ({error})") from None
    if not isinstance(summary, dict) or not isinstance(summary.get("tasks"), dict):
        raise AppError(f"{path}: not an rtloop summary (no tasks)")
    if summary.get("mode") != "run":
        raise AppError(f"{run_dir}: a {summary.get('mode')} run: only real-time runs have misses to explain")
    for name, task in summary["tasks"].items():
        period_ns = task.get("period_ns") if isinstance(task, dict) else None
        if isinstance(period_ns, bool) or not isinstance(period_ns, int) or period_ns <= 0:
            raise AppError(f"{path}: tasks.{name}: not an rtloop summary's task (no period_ns > 0)")
    if not isinstance(summary.get("misses") or {}, dict):
        raise AppError(f"{path}: misses: not an rtloop summary's (a table expected)")
    return summary


def _bounded_lines(file: Any, path: Path) -> Any:
    """``file``'s lines, each refused past :data:`TIMING_LINE_MAX_CHARS` (before it is read whole)."""
    while line := file.readline(TIMING_LINE_MAX_CHARS + 1):
        if len(line) > TIMING_LINE_MAX_CHARS:
            raise AppError(f"{path}: a line longer than {TIMING_LINE_MAX_CHARS} characters: not a timing.csv "
                           "rtloop wrote")
        yield line


def account(summary: dict[str, Any]) -> list[str]:
    """The run's misses: one line per task, kind and cause, then the first ones."""
    misses = summary.get("misses") or {}
    total = misses.get("total", 0)
    if not total and not misses.get("lines"):
        return [f"{summary['app']}: no deadline misses"]
    lines = [f"{summary['app']}: {total} deadline misses"]
    lines += [f"  {line}" for line in misses.get("lines", [])]
    first = misses.get("first", [])
    if first:
        lines.append(f"the first {len(first)}, in full (rtloop why RUN --cycle N --task T for the evidence):")
        lines += [f"  {m['task']} cycle {m['cycle']}: {m['kind']}: {m['cause']}" for m in first[:20]]
    return lines


def explain_cycle(run_dir: Path, summary: dict[str, Any], cycle: int, task: str | None) -> list[str]:
    kept = [m for m in (summary.get("misses") or {}).get("first", [])
            if m["cycle"] == cycle and (task is None or m["task"] == task)]
    lines: list[str] = []
    for miss in kept:
        lines += _evidence_lines(miss, summary)
    done = {m["task"] for m in kept}
    names = [task] if task is not None else [name for name in summary["tasks"] if name not in done]
    if names:
        lines += _from_timing_csv(run_dir, summary, cycle, [n for n in names if n not in done], refuse=not kept)
    return lines


def _evidence_lines(miss: dict[str, Any], summary: dict[str, Any]) -> list[str]:
    from rtloop.stats.miss_causes import ms

    task = summary["tasks"].get(miss["task"], {})
    period_ns = task.get("period_ns", 0)
    ev = miss.get("evidence", {})
    lines = [f"{miss['task']} cycle {miss['cycle']}: {miss['kind']}",
             f"  cause: {miss['cause']}",
             f"  its timing: woke {ms(miss['latency_ns'])} after its release, step took {ms(miss['exec_ns'])}, "
             f"period {ms(period_ns)}" + (f"; {miss['skipped']} releases skipped after it" if miss["skipped"] else ""),
             f"  the task: {task.get('policy')} priority {task.get('priority')} on CPU {ev.get('cpu')}"]
    counters = ev.get("counters")
    if counters:
        since = ("this cycle alone" if counters.get("bracketed")
                 else f"since its reading after cycle {counters['since_cycle']}" if counters["since_cycle"] >= 0
                 else "since before its first cycle")
        lines.append(f"  its thread's counters ({since}): on the CPU {ms(counters['on_cpu_ns'])}, waiting on the run "
                     f"queue {ms(counters['run_delay_ns'])}, {counters['involuntary_switches']} involuntary switches, "
                     f"{counters['minor_faults']} minor and {counters['major_faults']} major page faults")
    else:
        lines.append("  its thread's counters: not read for this cycle (a task reads them after its first 1000 "
                     "late cycles only)")
    if "window_ns" in ev:
        lines.append(f"  CPU {ev.get('cpu')} in the {ms(ev['window_ns'])} around it: steal {ms(ev['steal_ns'])}, "
                     f"IRQ and softirq {ms(ev['irq_ns'])} (/proc/stat, to a tick)")
    else:
        lines.append("  per-CPU steal and IRQ time: no sample of the supervisor around it")
    for other in ev.get("tasks", []):
        lines.append(f"  task {other['task']} ({other['relation']} priority {other['priority']}) "
                     f"cycle {other['cycle']}: its step ({ms(other['exec_ns'])}) overlapped {ms(other['overlap_ns'])}")
    for item in ev.get("traced", []):
        lines.append(f"  traced ({item['kind']}): {item['who']} had the CPU {ms(item['ran_ns'])} between the release "
                     "and the end")
    for thread in ev.get("threads", []):
        lines.append(f"  thread {thread['label']} ({thread['relation']} priority): ran {ms(thread['ran_ns'])} "
                     f"on the CPU in the {ms(thread.get('window_ns', ev.get('window_ns', 0)))} around it")
    for other in ev.get("simultaneous", []):
        lines.append(f"  task {other['task']} on CPU {other['cpu']} woke {ms(other['latency_ns'])} late at the same "
                     "instant")
    return lines


def _from_timing_csv(run_dir: Path, summary: dict[str, Any], cycle: int, names: list[str], *,
                     refuse: bool = False) -> list[str]:
    """Cycles not kept in full: their own timing and the other tasks' records, from timing.csv. ``refuse``: a
    cycle outside every named task's recorded cycles is bad input (a typo, another run's cycle)."""
    import numpy as np

    from rtloop.runtime.evidence import MissWatch, TaskFacts
    from rtloop.stats.miss_causes import Miss, explain, ms

    path = run_dir / "timing.csv"
    rows: dict[str, list[tuple[int, int, int, int]]] = {name: [] for name in summary["tasks"]}
    try:
        with _open_regular(path, f"{run_dir}: no timing.csv", "r") as file:
            for row in csv.DictReader(_bounded_lines(file, path)):
                if row.get("task") in rows:
                    rows[row["task"]].append((int(row["cycle"]), int(row["release_ns"]), int(row["start_ns"]),
                                              int(row["end_ns"])))
    except AppError:
        raise
    except (OSError, ValueError, KeyError, TypeError, csv.Error) as error:  # NUL bytes, a field too long: csv.Error
        raise AppError(f"{path}: cannot be read ({error})") from None
    facts = {name: TaskFacts(t["period_ns"], t.get("cpu"), t.get("priority", 0), bool(t.get("rt")))
             for name, t in summary["tasks"].items()}
    watch = MissWatch(facts=facts)
    outside = [f"{name}: {_recorded(rows[name])}" for name in names
               if not _span(rows[name])[0] <= cycle <= _span(rows[name])[1]]
    if refuse and len(outside) == len(names):
        raise AppError(f"{run_dir}: cycle {cycle} is not in this run's timing.csv ({'; '.join(outside)}): "
                       "give one of its cycles")
    lines: list[str] = []
    for name in names:
        records = sorted(rows[name])
        index = next((i for i, r in enumerate(records) if r[0] == cycle), None)
        if index is None:
            before = [r for r in records if r[0] < cycle]
            where = (f"a release skipped after cycle {before[-1][0]} overran" if before and any(
                r[0] > cycle for r in records) else f"not in timing.csv ({_recorded(records)})")
            lines.append(f"{name} cycle {cycle}: {where}")
            continue
        c, release, start, end = records[index]
        period = facts[name].period_ns
        if end <= release + period:
            lines.append(f"{name} cycle {cycle}: on time (woke {ms(start - release)} after its release, step took "
                         f"{ms(end - start)}, period {ms(period)})")
            continue
        for other, other_rows in rows.items():
            near = [r for r in other_rows if abs(r[1] - release) <= NEAR_NS]
            if near:
                watch.records[other].append(np.array(sorted(near), dtype=np.int64))
        after = records[index + 1][0] if index + 1 < len(records) else c + 1
        miss = Miss(name, c, release, start, end, period, max(0, after - c - 1))
        evidence = watch.evidence_for(miss, records[index - 1][0] if index else -1)
        cause = explain(miss, evidence)
        block = _evidence_lines({"task": name, "cycle": c, "kind": miss.kind, "cause": cause.text,
                                 "latency_ns": miss.latency_ns, "exec_ns": miss.exec_ns, "skipped": miss.skipped,
                                 "evidence": evidence.to_json()}, summary)
        block.insert(1, "  (not among the misses kept in full in summary.json: explained again from timing.csv "
                        "alone, without the machine's samples and the thread's counters)")
        lines += block
    return [line for line in lines if line]


def _span(records: list[tuple[int, int, int, int]]) -> tuple[int, int]:
    """(first, last) cycle recorded; (0, -1) when none is."""
    cycles = [r[0] for r in records]
    return (min(cycles), max(cycles)) if cycles else (0, -1)


def _recorded(records: list[tuple[int, int, int, int]]) -> str:
    first, last = _span(records)
    return f"cycles {first} to {last} recorded" if last >= first else "no cycle recorded"
