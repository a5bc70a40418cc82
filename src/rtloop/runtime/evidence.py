"""The supervisor's side of "why was that cycle late": evidence gathered between drains.

``MissWatch`` hears every drained timing record (``Recorder.listeners``) and every task's
counters read after a late cycle (a ``late`` pipe message), samples per-CPU steal and IRQ time
and the real-time threads of the machine at each drain (``after_drain``), and decides each miss's
cause one drain later, when the other tasks' records of the same instant and the sample after it
are in (``stats/miss_causes.py``). A task that was on time is never asked anything.
"""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from rtloop.linux import cpustat
from rtloop.stats.miss_causes import UNEXPLAINED, Cause, Evidence, Miss, MissLedger, explain

SAMPLES_KEPT = 400
"""Supervisor samples kept (one per drain, 50 ms: 20 s), enough for the misses still to decide."""
RECORDS_KEPT_NS = 2_000_000_000
"""How far back each task's records are kept, for the other tasks' misses at the same instant."""
THREAD_SCAN_INTERVAL_NS = 1_000_000_000
"""How often /proc is walked for real-time threads (~15 ms of the supervisor's time on a loaded VM)."""
THREAD_SCAN_MIN_INTERVAL_NS = 200_000_000
"""How soon a miss waiting for a walk after it may ask for one (a thread started just before it)."""
DECIDED_KEPT = 4096
EXAMINED_PER_DECISION = 500
"""Misses examined in full at one decision (a drain, or the end of the run): the evidence of one
costs a look through its task's recent records, so a flood of misses (a task far behind at a
high rate) would cost the supervisor more than the run; the others are counted, not examined."""
"""Misses whose causes are kept for the tasks they held up (decided in release order)."""
COUNTER_FIELDS = cpustat.THREAD_COUNTERS[1:]
"""The task's counters compared between two readings (the first field is when each was read)."""


@dataclass(frozen=True)
class Sample:
    at_ns: int
    cpus: dict[int, cpustat.CpuTimes]
    threads: dict[tuple[int, int], cpustat.ThreadInfo]
    scanned_ns: int
    """When /proc was last walked for real-time threads (a thread started since is not in ``threads``)."""


@dataclass(frozen=True)
class TaskFacts:
    period_ns: int
    cpu: int | None
    priority: int
    realtime: bool


class MissWatch:
    """Every miss of a run, with its cause (``ledger``); fed by the supervisor and the recorder."""

    def __init__(self, app: Any = None, facts: dict[str, TaskFacts] | None = None) -> None:
        self.facts = facts if facts is not None else {
            name: TaskFacts(spec.config.period_ns, spec.config.cpu, spec.config.priority,
                            spec.config.policy != "other")
            for name, spec in app.tasks.items()}
        self.ledger = MissLedger()
        self.samples: collections.deque[Sample] = collections.deque(maxlen=SAMPLES_KEPT)
        self.records: dict[str, collections.deque[np.ndarray]] = {name: collections.deque() for name in self.facts}
        self.last_cycle: dict[str, int] = {}
        self.pending: list[tuple[Miss, int]] = []
        """Misses waiting for the sample after them: (miss, the cycle the task ran just before it)."""
        self.readings: dict[str, dict[int, tuple[int, tuple[int, ...], tuple[int, ...]]]] = {}
        """Per task, cycle → (the cycle of the reading before, the reading before, this reading)."""
        self.previous_reading: dict[str, tuple[int, tuple[int, ...]]] = {}
        self.thread_ids: list[tuple[int, int]] = []
        self.scanned_ns = 0
        self.scan_cost_ns = 0
        self.task_pids: frozenset[int] = frozenset()
        self.tracer: Any = None
        """``linux/trace.py:MissTracer`` with --trace-misses on a kernel that has the events."""
        self.decided: dict[tuple[str, int], tuple[str, str]] = {}
        """The latest misses' causes, (task, cycle) → (class, text): a task held by another's late step
        is late for that step's reason."""

    # --- what the recorder and the pipes bring ---------------------------------------------------
    def add_timing(self, task: str, records: np.ndarray) -> None:
        """A drained batch of ``task``'s ``(cycle, release, start, end)`` records."""
        if not len(records) or task not in self.facts:
            return
        facts = self.facts[task]
        kept = self.records[task]
        kept.append(records)
        while len(kept) > 1 and kept[0][-1, 1] < records[-1, 1] - RECORDS_KEPT_NS:
            kept.popleft()
        late = np.flatnonzero(records[:, 3] > records[:, 1] + facts.period_ns)
        cycles = records[:, 0]
        for i in late.tolist():
            cycle, release, start, end = (int(v) for v in records[i])
            before = int(cycles[i - 1]) if i else self.last_cycle.get(task, -1)
            after = int(cycles[i + 1]) if i + 1 < len(records) else None
            skipped = max(0, after - cycle - 1) if after is not None else 0
            self.pending.append((Miss(task, cycle, release, start, end, facts.period_ns, skipped), before))
        self.last_cycle[task] = int(cycles[-1])

    def add_reads(self, task: str, writers: list[str], records: np.ndarray) -> None:
        """Stale reads of ``task`` (read-log records: release, writer index, stamp got, stamp due)."""
        for index, count in zip(*np.unique(records[:, 1], return_counts=True), strict=True):
            writer = writers[int(index)] if 0 <= index < len(writers) else f"writer {index}"
            self.ledger.add_stale(task, writer, int(count))

    def ran_realtime(self, task: str, realtime: bool) -> None:
        """What the task process got (its ``settings``): a task declared at SCHED_FIFO that was refused it
        runs at SCHED_OTHER, where any real-time thread preempts it and its run-queue wait is the evidence."""
        facts = self.facts.get(task)
        if facts is not None and facts.realtime != realtime:
            self.facts[task] = replace(facts, realtime=realtime)

    def from_task(self, task: str, message: dict[str, Any]) -> None:
        """A task's pipe message: ``late`` (its counters after a late cycle) or ``stopped``."""
        if message.get("kind") == "stopped":
            if message.get("catch_up_steps"):
                self.ledger.catch_up[task] = int(message["catch_up_steps"])
            return
        cycle, reading = int(message["cycle"]), tuple(message["counters"])
        before_cycle, before = self.previous_reading.get(task, (-1, tuple(message.get("baseline") or reading)))
        self.readings.setdefault(task, {})[cycle] = (before_cycle, before, reading)
        self.previous_reading[task] = (cycle, reading)

    # --- the kernel's trace events (--trace-misses) ------------------------------------------------
    def start_tracing(self) -> str:
        """Arm the scheduler and IRQ events on the pinned tasks' CPUs; '' or why they are not there."""
        from rtloop.linux.trace import open_tracer

        cpus = {facts.cpu for facts in self.facts.values() if facts.cpu is not None}
        if not cpus:
            return "no task is pinned to a CPU (cpu = N): there is no CPU to trace"
        self.tracer, why = open_tracer(cpus)
        return why

    def close(self) -> None:
        if self.tracer is not None:
            self.tracer.poll()  # the last events, before the buffers go
            self.finish()
            self.tracer.close()
            self.tracer = None

    # --- between drains --------------------------------------------------------------------------
    def after_drain(self, now_ns: int, task_pids: frozenset[int] = frozenset()) -> None:
        """Sample the machine, then decide the misses the sample before this one already covered."""
        self.task_pids = task_pids
        if self.tracer is not None:
            self.tracer.poll()
        since_scan_ns = now_ns - self.scanned_ns
        waiting = any(miss.end_ns > self.scanned_ns for miss, _ in self.pending)
        # a walk costs ~15 ms (more on a loaded machine): never more than a tenth of the supervisor's time
        soonest_ns = max(THREAD_SCAN_MIN_INTERVAL_NS, 10 * self.scan_cost_ns)
        if since_scan_ns >= max(THREAD_SCAN_INTERVAL_NS, soonest_ns) or (waiting and since_scan_ns >= soonest_ns):
            self.thread_ids = cpustat.realtime_threads(exclude_pids=task_pids)
            self.scanned_ns = now_ns
            self.scan_cost_ns = time.monotonic_ns() - now_ns
        threads = {}
        for pid, tid in self.thread_ids:
            info = cpustat.read_thread(pid, tid)
            if info is not None:
                threads[(pid, tid)] = info
        self.samples.append(Sample(now_ns, cpustat.read_cpu_times(), threads, self.scanned_ns))
        # Decided once a walk of /proc after the miss has been sampled: a thread that started just
        # before it (a test's hog, another app's task) is then known.
        ready = [p for p in self.pending if p[0].end_ns <= self.scanned_ns]
        self._decide(ready)
        self.pending = [p for p in self.pending if p[0].end_ns > self.scanned_ns]

    def finish(self) -> None:
        """Decide every miss still waiting (the run is over: no sample will come after them)."""
        if self.pending:
            self.scanned_ns = 0  # a last walk of /proc, for threads started since the last one
            self.after_drain(time.monotonic_ns(), self.task_pids)
        self._decide(self.pending)
        self.pending = []

    def summary(self, final: bool) -> dict[str, Any]:
        if final:
            self.finish()
        return self.ledger.to_json()

    # --- deciding ----------------------------------------------------------------------------------
    def _decide(self, misses: list[tuple[Miss, int]]) -> None:
        # in release order, a higher priority first: a step that held another is decided before it
        ordered = sorted(misses, key=lambda p: (p[0].release_ns, -self.facts[p[0].task].priority))
        if len(ordered) > EXAMINED_PER_DECISION:
            flood = Cause(UNEXPLAINED, f"not examined: {len(ordered)} misses came at once, more than the "
                                       f"{EXAMINED_PER_DECISION} the supervisor examines together")
            for miss, _before in ordered[EXAMINED_PER_DECISION:]:
                self.ledger.add(miss, Evidence(), flood)
            ordered = ordered[:EXAMINED_PER_DECISION]
        for miss, before in ordered:
            evidence = self.evidence_for(miss, before)
            cause = explain(miss, evidence)
            self.ledger.add(miss, evidence, cause)
            self.decided[(miss.task, miss.cycle)] = (cause.cls, cause.text)
            if len(self.decided) > DECIDED_KEPT:
                del self.decided[next(iter(self.decided))]

    def evidence_for(self, miss: Miss, cycle_before: int) -> Evidence:
        facts = self.facts[miss.task]
        evidence = Evidence(cpu=facts.cpu, realtime=facts.realtime, priority=facts.priority)
        self._window(miss, facts, evidence)
        self._same_cpu_tasks(miss, facts, evidence)
        self._simultaneous(miss, facts, evidence)
        if self.tracer is not None and facts.cpu is not None:
            evidence.traced = self.tracer.held(facts.cpu, miss.release_ns, miss.end_ns, self.task_pids)
        reading = self.readings.get(miss.task, {}).pop(miss.cycle, None)
        if reading is not None:
            before_cycle, before, now = reading
            deltas = {name: now[i + 1] - before[i + 1] if now[i + 1] >= 0 and before[i + 1] >= 0 else -1
                      for i, name in enumerate(COUNTER_FIELDS)}
            evidence.counters = {"since_cycle": before_cycle, "bracketed": int(before_cycle == cycle_before
                                                                               and cycle_before >= 0), **deltas}
        return evidence

    def _window(self, miss: Miss, facts: TaskFacts, evidence: Evidence) -> None:
        """Steal, IRQ time and real-time threads between the samples around the cycle."""
        before = next((s for s in reversed(self.samples) if s.at_ns <= miss.release_ns), None)
        after = next((s for s in self.samples if s.at_ns >= miss.end_ns), None)
        if before is None or after is None:
            return
        evidence.window_ns = after.at_ns - before.at_ns
        self._cpu_times(before, after, facts, evidence)
        # threads: the first sample that knew every thread started before the miss ended
        after = next((s for s in self.samples if s.at_ns >= miss.end_ns and s.scanned_ns >= miss.end_ns), after)
        for key, info in after.threads.items():
            old_info = before.threads.get(key)
            if info.on_cpu_ns < 0 or key[0] in self.task_pids:
                continue
            if old_info is None:  # not known then: it counts only if it started since
                if info.started_ns < before.at_ns:
                    continue
                ran_ns, old_cpu = info.on_cpu_ns, info.cpu
            else:
                ran_ns, old_cpu = info.on_cpu_ns - old_info.on_cpu_ns, old_info.cpu
            on_cpu = facts.cpu is None or facts.cpu in (info.cpu, old_cpu)
            if ran_ns <= 0 or not on_cpu:
                continue
            relation = ("higher" if not facts.realtime or info.priority > facts.priority
                        else "same" if info.priority == facts.priority else "lower")
            if relation != "lower":
                evidence.threads.append({"label": info.label(), "priority": info.priority, "relation": relation,
                                         "ran_ns": ran_ns, "window_ns": after.at_ns - before.at_ns})

    @staticmethod
    def _cpu_times(before: Sample, after: Sample, facts: TaskFacts, evidence: Evidence) -> None:
        """Steal and IRQ time on the task's CPU (every CPU's largest, for a task not pinned)."""
        cpus = [facts.cpu] if facts.cpu is not None else list(after.cpus)
        for cpu in cpus:
            old, new = before.cpus.get(cpu), after.cpus.get(cpu)
            if old is not None and new is not None:
                evidence.steal_ns = max(evidence.steal_ns, new.steal_ns - old.steal_ns)
                evidence.irq_ns = max(evidence.irq_ns, new.irq_ns + new.softirq_ns - old.irq_ns - old.softirq_ns)

    def _same_cpu_tasks(self, miss: Miss, facts: TaskFacts, evidence: Evidence) -> None:
        """Other tasks' steps on the same CPU that ran between the release and the end of the cycle."""
        for name, other in self.facts.items():
            if name == miss.task or (facts.cpu is not None and other.cpu != facts.cpu):
                continue
            if facts.realtime and other.realtime and other.priority < facts.priority:
                continue  # a lower priority cannot hold a real-time task
            relation = "higher" if other.priority > facts.priority or not facts.realtime else "same"
            for records in self.records[name]:
                starts, ends = records[:, 2], records[:, 3]
                overlap = np.minimum(ends, miss.end_ns) - np.maximum(starts, miss.release_ns)
                for i in np.flatnonzero(overlap > 0).tolist():
                    cycle = int(records[i, 0])
                    step: dict[str, Any] = {"task": name, "cycle": cycle, "overlap_ns": int(overlap[i]),
                                            "exec_ns": int(ends[i] - starts[i]), "priority": other.priority,
                                            "relation": relation}
                    decided = self.decided.get((name, cycle))
                    if decided is not None:
                        step["cause_class"], step["cause"] = decided
                    evidence.tasks.append(step)

    def _simultaneous(self, miss: Miss, facts: TaskFacts, evidence: Evidence) -> None:
        """Tasks on other CPUs that woke late at the same instant (the machine, not a step)."""
        for name, other in self.facts.items():
            if name == miss.task or facts.cpu is None or other.cpu is None or other.cpu == facts.cpu:
                continue
            worst = 0
            for records in self.records[name]:
                starts, releases = records[:, 2], records[:, 1]
                near = (releases <= miss.start_ns) & (starts >= miss.release_ns)
                if near.any():
                    worst = max(worst, int((starts[near] - releases[near]).max()))
            if worst > 0:
                evidence.simultaneous.append({"task": name, "cpu": other.cpu, "latency_ns": worst})
