"""Why a cycle was late: a cause for every miss, decided after the fact from cheap evidence.

Pure functions and a bounded ledger; the evidence is gathered by ``runtime/evidence.py`` (the
supervisor's samples of /proc, the other tasks' timing records, the task's own counters read only
after a late cycle). Nothing here runs in a task.

A miss is a cycle that ended after its deadline (release + P). Its **kind** says what made it
late: a **late wake-up** (it started late: ``start − release`` is the larger part) or an
**overrun** (its execution, ``end − start``, is). The **cause** names who took the time:

1. the step itself (``step overran``) — only when the cycle's execution time reached the period and
   nothing else took that time (the thread's own CPU time, when known, says how much was the step);
2. another rtloop task on the same CPU whose step ran meanwhile at a higher or the same priority;
3. another thread at a higher (or the same) real-time priority that ran on the CPU meanwhile;
4. the machine: steal time on the CPU (the hypervisor stalled it), or several tasks late at the
   same instant on different CPUs;
5. interrupts (IRQ and softirq time on the CPU);
6. a wait on the run queue the thread's own counters show, by threads not named otherwise;
7. page faults (the thread's counters);
8. otherwise ``unexplained`` (this kernel has no timerlat/osnoise tracer to ask).

A candidate explains a miss only if the time it took is at least half the time the cycle lost;
among those the first in the order above wins (a named thread before a generic stall).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

FIRST_IN_FULL = 20
"""Misses kept in ``summary.json`` with their evidence (about 1 KB each: the summary must stay within its
64 KiB bound, ``SUMMARY_BOUND_BYTES``); the rest are counted per cause."""
EVIDENCE_ITEMS = 3
"""Other tasks' steps, threads and late tasks kept per miss: the largest."""
RECENT_READING_CYCLES = 20
"""A task's counters read this few cycles before a miss still say how long it waited in it."""
SUFFICIENT = 0.5
"""A candidate explains a miss when it took at least this share of the time the cycle lost."""

LATE_WAKE_UP, OVERRUN, SKIPPED, STALE = "late wake-up", "overrun", "skipped release", "stale read"
STEP, TASK, THREAD, MACHINE, IRQ, RUN_QUEUE, FAULTS, UNEXPLAINED = (
    "step", "task", "thread", "machine", "irq", "run queue", "page faults", "unexplained")
CLASS_ORDER = (STEP, TASK, THREAD, MACHINE, IRQ, RUN_QUEUE, FAULTS, UNEXPLAINED)


def ms(value_ns: float) -> str:
    """A duration for a sentence: µs below 1 ms, else ms with one decimal."""
    if abs(value_ns) < 1_000_000:
        return f"{value_ns / 1e3:.0f} µs"
    return f"{value_ns / 1e6:.1f} ms"


@dataclass(frozen=True)
class Miss:
    """One cycle that ended after its deadline (times in CLOCK_MONOTONIC ns)."""

    task: str
    cycle: int
    release_ns: int
    start_ns: int
    end_ns: int
    period_ns: int
    skipped: int = 0
    """Releases skipped after it (``overrun = "skip"``)."""

    @property
    def latency_ns(self) -> int:
        return self.start_ns - self.release_ns

    @property
    def exec_ns(self) -> int:
        return self.end_ns - self.start_ns

    @property
    def kind(self) -> str:
        return LATE_WAKE_UP if self.latency_ns >= self.exec_ns else OVERRUN


@dataclass
class Evidence:
    """What is known about the time around one miss; every field may be empty."""

    cpu: int | None = None
    realtime: bool = True
    priority: int = 0
    """The task's real-time priority (what a traced thread's is compared with)."""
    """The task's policy is a real-time one (else SCHED_OTHER: it shares the CPU with every thread)."""
    window_ns: int = 0
    """The span of the supervisor's samples around the miss (steal, IRQ, threads are per window)."""
    steal_ns: int = 0
    irq_ns: int = 0
    tasks: list[dict[str, Any]] = field(default_factory=list)
    """Other rtloop tasks' steps on the same CPU overlapping the cycle: task, cycle, overlap_ns,
    exec_ns, priority, relation (``higher``/``same``)."""
    threads: list[dict[str, Any]] = field(default_factory=list)
    """Other threads at a real-time priority ≥ the task's that ran on the CPU in the window:
    label, priority, relation, ran_ns."""
    simultaneous: list[dict[str, Any]] = field(default_factory=list)
    """Other tasks (other CPUs) that woke late at the same instant: task, cpu, latency_ns."""
    traced: list[dict[str, Any]] = field(default_factory=list)
    """With --trace-misses: who had the CPU between the release and the end, from the kernel's
    scheduler and IRQ events (who, kind ``thread``/``irq``/``softirq``, ran_ns)."""
    counters: dict[str, int] | None = None
    """The task's own counters since its previous reading: since_cycle, bracketed (1: the reading
    before was at the cycle it ran just before, so these are this cycle's), on_cpu_ns,
    run_delay_ns, involuntary_switches, minor_faults, major_faults."""

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"cpu": self.cpu}
        if self.window_ns:
            out.update(window_ns=self.window_ns, steal_ns=self.steal_ns, irq_ns=self.irq_ns)
        largest = {"tasks": "overlap_ns", "threads": "ran_ns", "simultaneous": "latency_ns", "traced": "ran_ns"}
        for key, size in largest.items():
            if getattr(self, key):
                out[key] = sorted(getattr(self, key), key=lambda item: -item[size])[:EVIDENCE_ITEMS]
        if self.counters is not None:
            out["counters"] = self.counters
        return out


@dataclass(frozen=True)
class Cause:
    cls: str
    """One of ``CLASS_ORDER``."""
    text: str
    """The sentence: who took the time, with the numbers."""


def explain(miss: Miss, evidence: Evidence) -> Cause:
    """The cause of one miss, from its own timing and the evidence around it."""
    latency, exec_ns, period = miss.latency_ns, miss.exec_ns, miss.period_ns
    counters = evidence.counters or {}
    bracketed = bool(counters.get("bracketed")) and counters.get("on_cpu_ns", -1) >= 0
    recent = bracketed or 0 <= miss.cycle - counters.get("since_cycle", -1) <= RECENT_READING_CYCLES
    step_cpu_ns = counters["on_cpu_ns"] if bracketed else None
    timing = f"woke {ms(latency)} late, step took {ms(exec_ns)}"
    if miss.kind == LATE_WAKE_UP:
        lost_ns = latency
    else:
        timing = f"step took {ms(exec_ns)} of a {ms(period)} period (woke {ms(latency)} late)"
        if step_cpu_ns is not None:
            timing += f", {ms(step_cpu_ns)} of it on the CPU"
        if exec_ns >= period and step_cpu_ns is not None and (step_cpu_ns >= period or step_cpu_ns >= exec_ns / 2):
            return Cause(STEP, f"step overran: {ms(exec_ns)} of a {ms(period)} period"
                               f" ({ms(step_cpu_ns)} on the CPU)")
        lost_ns = exec_ns - step_cpu_ns if step_cpu_ns is not None else max(latency + exec_ns - period, 1)
    found = _interference(miss, evidence, lost_ns, counters if recent else {})
    if found is not None:
        return Cause(found.cls, f"{found.text}; {timing}")
    if miss.kind == OVERRUN and exec_ns >= period and step_cpu_ns is None:
        return Cause(STEP, f"step overran: {ms(exec_ns)} of a {ms(period)} period (nothing else ran meanwhile "
                           "as far as the evidence shows)")
    if evidence.traced:
        lower = evidence.traced[0]
        return Cause(UNEXPLAINED, f"unexplained: {timing}; the trace shows {lower['who']} on the CPU meanwhile, "
                                  "which cannot hold this task off: it was not runnable yet (a late timer, a stall "
                                  "the hypervisor did not report as steal, or RT throttling)")
    return Cause(UNEXPLAINED, f"unexplained: {timing}; no evidence names who held the CPU"
                 " (rtloop run --trace-misses can ask the kernel)")


def _interference(miss: Miss, ev: Evidence, lost_ns: int, counters: dict[str, int]) -> Cause | None:
    """The first candidate, in ``CLASS_ORDER``, that took at least half the time the cycle lost."""
    need_ns = SUFFICIENT * lost_ns
    cpu = f"CPU {ev.cpu}" if ev.cpu is not None else "a CPU (the task is not pinned)"
    waited_ns = counters.get("run_delay_ns", -1)
    if not ev.realtime and waited_ns >= need_ns:  # SCHED_OTHER: its own wait says more than any window
        return Cause(RUN_QUEUE, f"waited {ms(waited_ns)} on the run queue (SCHED_OTHER: it shares {cpu} with "
                                f"every other thread; {counters.get('involuntary_switches', 0)} involuntary switches)")
    # A thread below a real-time task's priority cannot hold it off: when the trace shows one on the CPU,
    # the task was not yet runnable (its timer fired late, the vCPU stalled, RT throttling): not that thread.
    traced = [t for t in ev.traced if t["ran_ns"] >= need_ns and (
        t["kind"] != "thread" or not ev.realtime or t.get("priority", -1) >= ev.priority)]
    if traced:  # the kernel's own events: exact, so first
        top = traced[0]
        higher = top.get("priority", -1) > ev.priority or (not ev.realtime and top.get("priority", -1) > 0)
        what = ("held by an interrupt handler" if top["kind"] != "thread" else
                "preempted by a higher-priority thread" if higher else "held by another thread")
        return Cause(IRQ if top["kind"] != "thread" else THREAD,
                     f"{what}: {top['who']} had {cpu} for {ms(top['ran_ns'])} of the cycle (traced)")
    for other in sorted(ev.tasks, key=lambda t: -t["overlap_ns"]):
        if other["overlap_ns"] >= need_ns:
            if ev.realtime:
                who = ("a higher-priority task" if other["relation"] == "higher" else "a task of the same priority")
                held = (f"held by {who}: {other['task']}'s step (cycle {other['cycle']}, {ms(other['exec_ns'])}, "
                        f"priority {other['priority']}) ran on {cpu} meanwhile")
            else:  # at SCHED_OTHER its declared priority was never applied: the kernel shared the CPU
                held = (f"held by another task (this one ran at SCHED_OTHER, not real time): {other['task']}'s step "
                        f"(cycle {other['cycle']}, {ms(other['exec_ns'])}) ran on {cpu} meanwhile")
            if other.get("cause_class") not in (None, STEP, UNEXPLAINED):  # that step was itself held up: by whom
                return Cause(other["cause_class"], f"{other['cause'].split('; ')[0]} (it held {other['task']}'s "
                                                   f"step, which held this one: {held})")
            return Cause(TASK, held)
    threads = [t for t in ev.threads if t["ran_ns"] >= need_ns]
    if threads:
        top = max(threads, key=lambda t: (t["relation"] == "higher", t["ran_ns"]))
        what = ("preempted by a higher-priority thread" if top["relation"] == "higher"
                else "a thread of the same real-time priority held the CPU")
        return Cause(THREAD, f"{what}: {top['label']} ran {ms(top['ran_ns'])} on {cpu} "
                             f"in the {ms(top.get('window_ns', ev.window_ns))} around it")
    if ev.steal_ns and ev.steal_ns >= need_ns:
        return Cause(MACHINE, f"the machine stalled (steal +{ms(ev.steal_ns)} on {cpu} in the "
                              f"{ms(ev.window_ns)} around it: the hypervisor ran something else)")
    late_too = [s for s in ev.simultaneous if s["latency_ns"] >= need_ns]
    if late_too:
        names = ", ".join(f"{s['task']} (CPU {s['cpu']}, {ms(s['latency_ns'])} late)" for s in late_too[:3])
        return Cause(MACHINE, f"the machine: other tasks woke late at the same instant: {names}")
    if ev.irq_ns and ev.irq_ns >= need_ns:
        return Cause(IRQ, f"interrupts: IRQ and softirq time +{ms(ev.irq_ns)} on {cpu} in the "
                          f"{ms(ev.window_ns)} around it")
    if counters.get("run_delay_ns", -1) >= need_ns:
        return Cause(RUN_QUEUE, f"waited {ms(counters['run_delay_ns'])} on the run queue (another thread held "
                                f"{cpu}: {counters.get('involuntary_switches', 0)} involuntary switches)")
    if counters.get("major_faults", 0) or counters.get("minor_faults", 0) >= 10:
        return Cause(FAULTS, f"page faults in the cycle: {counters.get('major_faults', 0)} major, "
                             f"{counters.get('minor_faults', 0)} minor")
    return None


@dataclass
class _Tally:
    count: int = 0
    skipped: int = 0
    worst_ns: int = 0
    example: str = ""
    holders: dict[str, int] = field(default_factory=dict)
    """THREAD causes: the threads named, and how often."""
    all_higher: bool = True
    """THREAD causes: every one a thread of a higher priority than the task's."""


def holder_of(text: str) -> str:
    """The thread a THREAD cause names ("preempted by …: NAME (pid …) ran 3 ms …" → "NAME (pid …)")."""
    named = text.split(": ", 1)[-1]
    return named.split(" ran ")[0].split(" had ")[0]


class MissLedger:
    """Every miss's cause, bounded: the first ``first_in_full`` in full, then counts per cause."""

    def __init__(self, first_in_full: int = FIRST_IN_FULL) -> None:
        self.first_in_full = first_in_full
        self.first: list[dict[str, Any]] = []
        self.tally: dict[tuple[str, str, str], _Tally] = {}
        self.total = 0
        self.stale: dict[tuple[str, str], int] = {}
        """(reader, writer) → stale reads."""
        self.catch_up: dict[str, int] = {}
        """Model tasks' extra steps after skipped releases (task → steps)."""

    def add(self, miss: Miss, evidence: Evidence, cause: Cause) -> None:
        self.total += 1
        tally = self.tally.setdefault((miss.task, miss.kind, cause.cls), _Tally())
        tally.count += 1
        tally.skipped += miss.skipped
        worst = miss.latency_ns if miss.kind == LATE_WAKE_UP else miss.exec_ns
        if worst >= tally.worst_ns:
            tally.worst_ns, tally.example = worst, cause.text
        if cause.cls == THREAD:
            holder = holder_of(cause.text)
            tally.holders[holder] = tally.holders.get(holder, 0) + 1
            tally.all_higher &= cause.text.startswith("preempted by a higher-priority thread")
        if len(self.first) < self.first_in_full:
            self.first.append({"task": miss.task, "cycle": miss.cycle, "kind": miss.kind, "cause_class": cause.cls,
                               "cause": cause.text, "release_ns": miss.release_ns, "latency_ns": miss.latency_ns,
                               "exec_ns": miss.exec_ns, "skipped": miss.skipped, "evidence": evidence.to_json()})

    def add_stale(self, reader: str, writer: str, count: int) -> None:
        self.stale[(reader, writer)] = self.stale.get((reader, writer), 0) + count

    def causes_of(self, task: str) -> list[str]:
        """The cause classes of ``task``'s misses, most frequent first."""
        counts: dict[str, int] = {}
        for (name, _kind, cls), tally in self.tally.items():
            if name == task:
                counts[cls] = counts.get(cls, 0) + tally.count
        return sorted(counts, key=lambda c: -counts[c])

    def lines(self) -> list[str]:
        """One line per task, kind and cause class: the console's and the notes' account."""
        out: list[str] = []
        order = {cls: i for i, cls in enumerate(CLASS_ORDER)}
        for (task, kind, cls), tally in sorted(self.tally.items(), key=lambda i: (i[0][0], i[0][1], order[i[0][2]])):
            plural = kind + ("s" if tally.count != 1 else "")
            skipped = f" ({tally.skipped} releases skipped)" if tally.skipped else ""
            share = "" if tally.count == 1 else ("all " if self._only(task, kind, cls) else f"{tally.count} ")
            phrase = _class_phrase(cls)
            if cls == THREAD:
                if not tally.all_higher:
                    phrase = "held by other threads (of a higher or the same priority)"
                top = sorted(tally.holders.items(), key=lambda item: -item[1])[:3]
                phrase += " (" + ", ".join(f"{who}: {n}" for who, n in top) + ")"
            out.append(f"{task}: {tally.count} {plural}{skipped}, {share}{phrase}; worst: {tally.example}")
        for (reader, writer), count in sorted(self.stale.items()):
            late = self.causes_of(writer)
            why = f" (its misses: {', '.join(_class_phrase(c) for c in late)})" if late else ""
            out.append(f"{reader}: {count} stale reads of {writer}: {writer} had not published in time{why}")
        for task, steps in sorted(self.catch_up.items()):
            out.append(self.catch_up_line(task, steps))
        return out

    def catch_up_line(self, task: str, steps: int) -> str:
        """The model adapter's account of its extra steps, naming the task and the true cause."""
        causes = self.causes_of(task)
        if not causes:
            why = "after skipped releases"
        elif causes == [STEP]:
            why = "because its step overran"
        else:
            why = "after misses caused by: " + ", ".join(_class_phrase(c) for c in causes)
            if STEP not in causes:
                why += " (not by its step)"
        return (f"{task}: the model took {steps} extra steps to keep its time equal to the clock's, {why}"
                " (rtloop why RUN --cycle N says more)")

    def _only(self, task: str, kind: str, cls: str) -> bool:
        return all(c == cls for (t, k, c) in self.tally if t == task and k == kind)

    def to_json(self) -> dict[str, Any]:
        counts: dict[str, dict[str, dict[str, int]]] = {}
        skipped: dict[str, dict[str, int]] = {}
        for (task, kind, cls), tally in self.tally.items():
            counts.setdefault(task, {}).setdefault(kind, {})[cls] = tally.count
            if tally.skipped:
                skipped.setdefault(task, {})[cls] = skipped.get(task, {}).get(cls, 0) + tally.skipped
        stale: dict[str, dict[str, int]] = {}
        for (reader, writer), count in self.stale.items():
            stale.setdefault(reader, {})[writer] = count
        return {"total": self.total, "in_full": len(self.first), "first": self.first, "counts": counts,
                "skipped_releases": skipped, "stale_reads": stale, "catch_up_steps": dict(self.catch_up),
                "lines": self.lines()}


def _class_phrase(cls: str) -> str:
    return {STEP: "the step overran", TASK: "another rtloop task held the CPU",
            THREAD: "preempted by a higher-priority thread", MACHINE: "while the machine stalled",
            IRQ: "interrupts held the CPU", RUN_QUEUE: "waited on the run queue", FAULTS: "page faults",
            UNEXPLAINED: "unexplained"}[cls]
