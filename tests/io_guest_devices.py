"""The test guest's device map, for the driver tests (``tools/rtkernel-vm.sh`` writes it).

Outside the guest, or when the guest could not set a device up, the tests that need it skip
and say why."""

from __future__ import annotations

import json
import os
import time
import tracemalloc
from pathlib import Path
from typing import Any

import pytest

GUEST_COMMAND = "tools/rtkernel-vm.sh .venv/bin/python -m pytest tests/test_io_*.py"


def guest_device(name: str) -> dict[str, Any]:
    """The entry ``name`` (vcan, can, gpio, spi, i2c, serial) of the guest's device map, or skip."""
    path = os.environ.get("RTLOOP_GUEST_DEVICES", "")
    if not os.environ.get("RTLOOP_GUEST") or not path:
        pytest.skip(f"needs the {name} device of the PREEMPT_RT test guest: run {GUEST_COMMAND}")
    devices = json.loads(Path(path).read_text())["devices"]
    entry = devices.get(name)
    if entry is None:
        pytest.skip(f"the test guest has no {name} device")
    if not entry.get("present"):
        pytest.skip(f"the test guest could not set up {name}: {entry.get('reason', '?')}")
    return entry


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
