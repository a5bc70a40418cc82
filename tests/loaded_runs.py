"""Runs that miss deadlines on purpose, for the tests of what a miss leaves behind (its cause, its
replay): JIWY's two tasks at 1 kHz on one CPU, and stress-ng loading the machine beside them."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
from collections.abc import Iterator

JIWY_ON_ONE_CPU = """name = "{name}"
[tasks.controller]
runnable = "jiwy_models:JiwyController"
period_ns = 1_000_000
priority = 80
cpu = {cpu}
[tasks.plant]
runnable = "jiwy_models:JiwyPlant"
period_ns = 1_000_000
priority = 81
cpu = {cpu}
[[connect]]
from = "plant.y[0:2]"
to = "controller.u[0:2]"
[[connect]]
from = "controller.y[0:2]"
to = "plant.u[0:2]"
"""
"""An app file (``format(name=..., cpu=...)``): the controller and the plant, each feeding the other."""


@contextlib.contextmanager
def stress_ng(*args: str) -> Iterator[None]:
    """``stress-ng ARGS --quiet`` while the block runs, in a session of its own so that exactly its
    process group is stopped afterwards (SIGTERM, then reaped). The caller skips where it is missing."""
    hogs = subprocess.Popen(["stress-ng", *args, "--quiet"], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        yield
    finally:
        os.killpg(hogs.pid, signal.SIGTERM)
        hogs.wait(timeout=30)
