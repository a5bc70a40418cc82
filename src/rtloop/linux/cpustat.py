"""Cheap counters the kernel keeps anyway: what a late cycle's cause is decided from.

- per CPU, from ``/proc/stat``: steal (the hypervisor ran someone else on this virtual CPU), IRQ
  and softirq time, in USER_HZ ticks (10 ms here: a stall shorter than a tick may show as 0 or 10 ms);
- per thread, from ``/proc/PID/task/TID/stat`` and ``schedstat`` (``CONFIG_SCHED_INFO``): its
  scheduling policy and priority, the CPU it last ran on, its time on the CPU and its run-queue wait;
- a thread's own ``getrusage(RUSAGE_THREAD)``: page faults and context switches.

Nothing here runs in a cycle that was on time: the supervisor samples the first two between drains,
and a task reads its own counters (:func:`own_thread_counters`) only after a cycle that missed.
"""

from __future__ import annotations

import os
import resource
import time
from dataclasses import dataclass

TICK_NS = 1_000_000_000 // os.sysconf("SC_CLK_TCK")
"""One USER_HZ tick of /proc/stat, in ns."""
_BOOT_TO_MONOTONIC_NS = time.clock_gettime_ns(time.CLOCK_BOOTTIME) - time.monotonic_ns()
"""CLOCK_BOOTTIME (/proc's start times) minus CLOCK_MONOTONIC (the tasks' records): the time suspended."""
POLICY_NAMES = {0: "other", 1: "fifo", 2: "rr", 3: "batch", 5: "idle", 6: "deadline"}


@dataclass(frozen=True)
class CpuTimes:
    """Cumulative time one CPU spent in steal, IRQ and softirq (ns, at tick resolution)."""

    steal_ns: int
    irq_ns: int
    softirq_ns: int


def read_cpu_times(path: str = "/proc/stat") -> dict[int, CpuTimes]:
    """Per CPU number, its steal/IRQ/softirq time so far; {} where /proc/stat cannot be read."""
    times: dict[int, CpuTimes] = {}
    try:
        with open(path, encoding="ascii") as file:
            for line in file:
                if not line.startswith("cpu") or line.startswith("cpu "):
                    if times:  # the cpuN lines come together, right after the total
                        break
                    continue
                fields = line.split()
                # cpuN user nice system idle iowait irq softirq steal ...
                values = [int(v) for v in fields[1:9]] + [0] * max(0, 9 - len(fields))
                times[int(fields[0][3:])] = CpuTimes(values[7] * TICK_NS, values[5] * TICK_NS,
                                                     values[6] * TICK_NS)
    except (OSError, ValueError):
        return {}
    return times


@dataclass(frozen=True)
class ThreadInfo:
    """A thread as /proc shows it now."""

    pid: int
    tid: int
    name: str
    policy: str
    priority: int
    cpu: int
    """The CPU it ran on last."""
    on_cpu_ns: int
    """Its time on a CPU so far (schedstat), -1 unknown."""
    started_ns: int = 0
    """When it started, on CLOCK_MONOTONIC (to a tick)."""

    @property
    def realtime(self) -> bool:
        return self.policy in ("fifo", "rr", "deadline")

    def label(self) -> str:
        return f"{self.name} (pid {self.pid}, tid {self.tid}, {self.policy.upper()} {self.priority})"


def read_thread(pid: int, tid: int) -> ThreadInfo | None:
    """One thread's policy, priority, last CPU and CPU time; None when it is gone or unreadable."""
    base = f"/proc/{pid}/task/{tid}"
    try:
        with open(f"{base}/stat", "rb") as file:
            stat = file.read().decode("utf-8", "replace")
        with open(f"{base}/schedstat", "rb") as file:
            schedstat = file.read().split()
    except OSError:
        return None
    close = stat.rfind(")")
    name = stat[stat.find("(") + 1:close]
    fields = stat[close + 2:].split()  # fields[0] is field 3 (state) of proc(5)
    try:
        cpu, rt_priority, policy = int(fields[36]), int(fields[37]), int(fields[38])
        on_cpu_ns = int(schedstat[0]) if schedstat else -1
        started_ns = int(fields[19]) * TICK_NS - _BOOT_TO_MONOTONIC_NS  # field 22: since boot, in ticks
    except (IndexError, ValueError):
        return None
    return ThreadInfo(pid, tid, name, POLICY_NAMES.get(policy, str(policy)), rt_priority, cpu, on_cpu_ns,
                      started_ns)


def realtime_threads(exclude_pids: frozenset[int] = frozenset()) -> list[tuple[int, int]]:
    """(pid, tid) of every thread on the machine at a real-time policy (a walk of /proc: ~ms; seldom)."""
    found: list[tuple[int, int]] = []
    try:
        pids = [int(name) for name in os.listdir("/proc") if name.isdigit()]
    except OSError:
        return found
    for pid in pids:
        if pid in exclude_pids:
            continue
        try:
            tids = [int(name) for name in os.listdir(f"/proc/{pid}/task")]
        except OSError:
            continue
        for tid in tids:
            try:
                with open(f"/proc/{pid}/task/{tid}/stat", "rb") as file:
                    stat = file.read()
            except OSError:
                continue
            fields = stat[stat.rfind(b")") + 2:].split()
            if len(fields) > 38 and fields[38] in (b"1", b"2", b"6"):
                found.append((pid, tid))
    return found


THREAD_COUNTERS = ("at_ns", "on_cpu_ns", "run_delay_ns", "involuntary_switches", "minor_faults", "major_faults")
"""What :func:`own_thread_counters` returns, in order: when it read them (CLOCK_MONOTONIC), the thread's
CPU time (CLOCK_THREAD_CPUTIME_ID), its run-queue wait (schedstat; -1 without CONFIG_SCHED_INFO), its
involuntary context switches and its minor and major page faults (getrusage(RUSAGE_THREAD)), so far."""


def own_thread_counters(now_ns: int) -> tuple[int, ...]:
    """The calling thread's counters (:data:`THREAD_COUNTERS`; a tuple: the pipe message stays small).

    Costs a few µs (one getrusage, one /proc read): call it only after a cycle that was late."""
    usage = resource.getrusage(resource.RUSAGE_THREAD)
    # The thread's own schedstat CPU time lags by up to a tick while it runs; this clock does not.
    on_cpu_ns = time.thread_time_ns()
    run_delay_ns = -1
    try:
        with open("/proc/thread-self/schedstat", "rb") as file:
            run_delay_ns = int(file.read().split()[1])  # updated when it is switched in: exact here
    except (OSError, IndexError, ValueError):
        pass  # a kernel without CONFIG_SCHED_INFO: the other counters still say something
    return (now_ns, on_cpu_ns, run_delay_ns, usage.ru_nivcsw, usage.ru_minflt, usage.ru_majflt)
