"""Helpers of the driver tests in the PREEMPT_RT test guest: gpio-sim lines, allocation counting."""

from __future__ import annotations

import time
import tracemalloc
from pathlib import Path
from typing import Any

# the guest's device map, as the guest's conftest reads it (skips outside the guest, with the reason)
from conftest import guest_device

__all__ = ["KEPT_BYTES_ALLOWED", "SimLine", "bytes_kept_by", "guest_device"]


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


def bytes_kept_by(cycle, cycles):
    """Memory that ``cycles`` calls of ``cycle`` leave allocated (tracemalloc; after a warm-up under it)."""
    tracemalloc.start()
    try:
        for _ in range(2_000):  # first calls fill caches and free lists (floats, struct codes): not growth
            cycle()
        before = tracemalloc.get_traced_memory()[0]
        for _ in range(cycles):
            cycle()
        return tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
