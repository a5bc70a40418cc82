"""How much memory each task process holds while it runs, and a note when it keeps growing.

A task runs with the garbage collector frozen and off (a collection is a pause of unbounded
length) and, when it may, with all its memory locked. A ``step`` that makes one reference
cycle per cycle (an exception kept in an attribute, a closure over ``self``, a parent/child
pair) then grows the task without bound until the run ends, and locked pages cannot be
reclaimed: over a week that is the machine's memory. The supervisor reads each task's
resident size from ``/proc`` when it rewrites ``summary.json`` (every 2 s), reports it per
task (``resident_bytes``: first, last, largest) and says in a note when it grew by more than
:data:`GROWTH_NOTE_BYTES`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

GROWTH_NOTE_BYTES = 32 * 1024 * 1024
"""Growth of a task's resident memory while it runs that earns a note."""
PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")


def resident_bytes(pid: int) -> int | None:
    """The resident size of process ``pid`` (None: gone, or not readable)."""
    try:
        with open(f"/proc/{pid}/statm", "rb") as file:
            return int(file.read().split()[1]) * PAGE_BYTES
    except (OSError, ValueError, IndexError):
        return None


@dataclass
class _Samples:
    first_bytes: int
    first_ns: int
    last_bytes: int
    last_ns: int
    max_bytes: int


class MemoryWatch:
    """The resident size of each task, sampled at the supervisor's summary rewrites."""

    def __init__(self) -> None:
        self.samples: dict[str, _Samples] = {}

    def sample(self, task: str, pid: int | None, elapsed_ns: int) -> None:
        size = resident_bytes(pid) if pid else None
        if size is None:
            return  # not started yet, or ended: the last sample stands
        seen = self.samples.get(task)
        if seen is None:
            self.samples[task] = _Samples(size, elapsed_ns, size, elapsed_ns, size)
            return
        seen.last_bytes, seen.last_ns = size, elapsed_ns
        seen.max_bytes = max(seen.max_bytes, size)

    def to_json(self, task: str) -> dict[str, int] | None:
        seen = self.samples.get(task)
        if seen is None:
            return None
        return {"first": seen.first_bytes, "last": seen.last_bytes, "max": seen.max_bytes}

    def notes(self) -> list[str]:
        notes = []
        for task, seen in self.samples.items():
            growth = seen.max_bytes - seen.first_bytes
            if growth <= GROWTH_NOTE_BYTES:
                continue
            span_s = max((seen.last_ns - seen.first_ns) / 1e9, 1e-9)
            notes.append(f"task {task}'s memory grew {growth / 2**20:.0f} MiB in {span_s:.0f} s "
                         f"({growth / 2**20 / span_s:.2g} MiB/s) while it ran, with the garbage collector off: "
                         "reference cycles made in step (a kept exception, a closure over self) stay until "
                         "the run ends; see docs/first-app.md")
        return notes
