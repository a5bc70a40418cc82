"""The kernel's view of one thread's wake-ups: did it wait on a futex (the interpreter's lock) between
waking from its sleep and sleeping again? For bench_switch.py --trace (root, tracefs).

A tracing instance of its own (``instances/bench-lock-waits-PID``: its own buffer, the machine's tracing
left alone) records the ``raw_syscalls`` of one thread only (``set_event_pid``), filtered to
``clock_nanosleep`` (230) and ``futex`` (202), and its own switches out (whom the CPU went to), stamped on
CLOCK_MONOTONIC (``trace_clock mono``, as
timing.csv). The loop's own thread is the task process's main thread, so its pid is the task's.
Tracing is switched on only while something is measured; the buffer is never cleared during a run (on
this VM's kernel, clearing a large buffer from a CPU the tasks use stalled them for 32 ms).
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

from rtloop.linux.trace import find_tracefs, mount_tracefs, unmount

SYS_FUTEX, SYS_CLOCK_NANOSLEEP = 202, 230
FUTEX_WAITS = (0, 9)
"""FUTEX_WAIT and FUTEX_WAIT_BITSET (pthread_cond_timedwait, the lock's hand-over), private flag aside."""
BUFFER_KB = 8192


class LockWaitTrace:
    def __init__(self) -> None:
        self.mounted: Path | None = None
        place = find_tracefs()
        if place is None:
            place = self.mounted = mount_tracefs()
        self.root = place / "instances" / f"bench-lock-waits-{os.getpid()}"
        self.root.mkdir()  # its buffers made now, before the tasks run
        self.switch(False)
        (self.root / "trace_clock").write_text("mono")
        (self.root / "buffer_size_kb").write_text(str(BUFFER_KB))

    def arm(self, pid: int) -> None:
        """Trace thread ``pid`` (tracing still off)."""
        (self.root / "set_event_pid").write_text(str(pid))
        for event in ("sys_enter", "sys_exit"):
            folder = self.root / "events" / "raw_syscalls" / event
            (folder / "filter").write_text(f"id == {SYS_FUTEX} || id == {SYS_CLOCK_NANOSLEEP}")
            (folder / "enable").write_text("1")
        (self.root / "events" / "sched" / "sched_switch" / "enable").write_text("1")  # its own: who gets the CPU

    def switch(self, on: bool) -> None:
        (self.root / "tracing_on").write_text("1" if on else "0")

    def wake_ups(self) -> list[tuple[int, int]]:
        """Each wake-up of the thread (its sleep's return, ns) and how long it then waited on futexes (ns)
        before sleeping again. :attr:`held_by` counts whom the CPU went to as it began such a wait."""
        found: list[tuple[int, int]] = []
        self.held_by: dict[str, int] = {}
        woke_ns = waited_ns = waiting_since = 0
        for line in (self.root / "trace").read_text().splitlines():
            if waiting_since and ": sched_switch:" in line:
                after = line.split("next_comm=", 1)[1]
                who = f"{after.split(' next_pid=')[0]} (pid {after.split('next_pid=')[1].split()[0]}, " \
                      f"kernel prio {after.split('next_prio=')[1].split()[0]})"
                self.held_by[who] = self.held_by.get(who, 0) + 1
                continue
            if line.startswith("#") or ": sys_e" not in line:
                continue
            head, _, rest = line.partition(": sys_e")
            seconds, _, fraction = head.rsplit(None, 1)[-1].rstrip(":").partition(".")
            at_ns = int(seconds) * 1_000_000_000 + int(fraction.ljust(9, "0")[:9])
            entering = rest.startswith("nter")
            number = int(rest.split("NR ", 1)[1].split()[0])
            if number == SYS_CLOCK_NANOSLEEP:
                if entering and woke_ns:
                    found.append((woke_ns, waited_ns))
                    woke_ns = 0
                elif not entering:
                    woke_ns, waited_ns = at_ns, 0
            elif number == SYS_FUTEX and woke_ns:
                if entering:
                    operation = int(rest.split("(", 1)[1].split(",")[1], 16) & 0x7F
                    waiting_since = at_ns if operation in FUTEX_WAITS else 0
                elif waiting_since:
                    waited_ns += at_ns - waiting_since
                    waiting_since = 0
        return found

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.switch(False)
        with contextlib.suppress(OSError):
            self.root.rmdir()
        if self.mounted is not None:
            unmount(self.mounted)


def waits_within(wake_ups: list[tuple[int, int]], windows: list[tuple[int, int]]) -> list[dict[str, Any]]:
    """Per window (from, to ns): the thread's wake-ups in it, how many waited on the lock, the longest wait."""
    out = []
    for start_ns, end_ns in windows:
        inside = [waited for woke, waited in wake_ups if start_ns <= woke <= end_ns]
        out.append({"wake_ups": len(inside), "waited": sum(1 for waited in inside if waited),
                    "longest_us": max(inside, default=0) / 1e3})
    return out
