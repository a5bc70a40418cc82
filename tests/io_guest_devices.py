"""Helpers of the driver tests in the PREEMPT_RT test guest: gpio-sim lines, allocation counting."""

from __future__ import annotations

import re
import time
import tracemalloc
from pathlib import Path
from typing import Any

# the guest's device map, as the guest's conftest reads it (skips outside the guest, with the reason)
from conftest import guest_device

__all__ = ["KEPT_BYTES_ALLOWED", "SimLine", "bytes_kept_by", "guest_device", "scope_values"]


class SimLine:
    """One line of gpio-sim: drive it as an input (``pull``), see it as an output (``value``)."""

    def __init__(self, gpio: dict[str, Any], name: str) -> None:
        self.offset = gpio["lines"][name]["offset"]
        self.folder = Path(gpio["sim"]) / f"sim_gpio{self.offset}"

    def pull(self, up: bool) -> None:
        (self.folder / "pull").write_text("pull-up" if up else "pull-down")

    @property
    def value(self) -> int:
        return int((self.folder / "value").read_text())

    def wait_value(self, wanted: int, timeout_s: float = 5.0) -> int:
        deadline = time.monotonic() + timeout_s
        while self.value != wanted and time.monotonic() < deadline:
            time.sleep(0.001)
        return self.value


# A loop that keeps one object per cycle keeps >= 240,000 bytes over 10,000 cycles; what the
# interpreter's free lists happen to hold at the end is a few dozen bytes, whatever the count.
KEPT_BYTES_ALLOWED = 256


NOT_XDIST = tracemalloc.Filter(False, "*/execnet/*", all_frames=True)
"""Leaves out another thread of the test process: xdist's, taking a message from its controller while the
cycles run (worksteal asks busy workers for tests), once added 1,266 bytes."""


def _traced_by_the_cycle() -> int:
    """Bytes traced, but neither those of xdist's thread nor those of this count itself (its snapshot,
    fnmatch's and re's caches)."""
    others = [NOT_XDIST, tracemalloc.Filter(False, tracemalloc.__file__, all_frames=True)]
    return sum(stat.size for stat in tracemalloc.take_snapshot().filter_traces(others).statistics("filename"))


def bytes_grown(before: tracemalloc.Snapshot, after: tracemalloc.Snapshot) -> int:
    """What the files whose allocations grew between two snapshots grew by, xdist's thread left out."""
    mine = [NOT_XDIST]
    return sum(stat.size_diff for stat in after.filter_traces(mine).compare_to(before.filter_traces(mine), "filename")
               if stat.size_diff > 0)


def bytes_kept_by(cycle, cycles):
    """Memory that ``cycles`` calls of ``cycle`` leave allocated (tracemalloc; after a warm-up under it)."""
    tracemalloc.start(64)  # frames enough to reach the thread's first (execnet's) or the count's (tracemalloc's)
    try:
        for _ in range(2_000):  # first calls fill caches and free lists (floats, struct codes): not growth
            cycle()
        before = _traced_by_the_cycle()
        for _ in range(cycles):
            cycle()
        return _traced_by_the_cycle() - before
    finally:
        tracemalloc.stop()


# One line of ``strace -ff`` per GPIO_V2_LINE_SET_VALUES_IOCTL call: the request's values as set
SET_VALUES = re.compile(r"^ioctl\((\d+), GPIO_V2_LINE_SET_VALUES_IOCTL, \{bits=(0x[0-9a-f]+|0), "
                        r"mask=(0x[0-9a-f]+|0)\}\) = 0$")


def scope_values(traces: Path) -> list[int]:
    """The scope pin's values, in the order the task set them: from each traced process's
    SET_VALUES ioctls with a one-bit mask (the pin's; the device's writes of its two outputs carry
    both their bits and never the pin's, docs/devices.md). Only one process (the task) may set it."""
    by_process = {}
    masks = set()
    for trace in traces.parent.glob(traces.name + ".*"):
        values = []
        for line in trace.read_text().splitlines():
            match = SET_VALUES.match(line)
            if match is None:
                continue
            bits, mask = int(match.group(2), 16), int(match.group(3), 16)
            if mask.bit_count() == 1:
                masks.add(mask)
                values.append(1 if bits & mask else 0)
        if values:
            by_process[trace.name] = values
    assert len(masks) <= 1 and len(by_process) <= 1, (masks, {name: len(v) for name, v in by_process.items()})
    return next(iter(by_process.values()), [])
