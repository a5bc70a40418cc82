"""Helpers of the EtherCAT drive tests (and of benchmarks/bench_ethercat_drives.py): a veth pair of
the test's own (``rtloop.io.drives.veth``), the emulated drives on one end, the JIWY EtherCAT
example adapted to them. Needs root (veth, raw sockets); skips otherwise."""

from __future__ import annotations

import itertools
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from rtloop.io.drives import veth
from rtloop.io.drives.veth import veth_problem

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "jiwy_ethercat"
_COUNTER = itertools.count()


def veth_pair() -> Iterator[tuple[str, str]]:
    """A veth pair named for this test alone (master end, slave end), up; deleted afterwards."""
    problem = veth_problem()
    if problem:
        pytest.skip(f"{problem}: the emulated EtherCAT drives")
    tag = f"{os.getpid() % 100000:05d}{next(_COUNTER) % 100:02d}"
    try:
        with veth.veth_pair(f"ecm{tag}", f"ecs{tag}") as pair:
            yield pair
    except veth.VethError as error:
        pytest.skip(str(error))


def example_app(folder: Path, master: str, slave: str, name: str, period_ms: float = 2, drives: int = 2,
                **replace: str) -> Path:
    """The JIWY EtherCAT example in ``folder``, on this veth pair, under ``name``, at ``period_ms``
    (the planner's time step and the drives' cycle with it, so the motion is the example's), with
    ``drives`` drives (beyond two: copies of pan, holding where they are)."""
    shutil.copy(EXAMPLE / "jiwy_trajectory.py", folder)
    text = (EXAMPLE / "jiwy_ethercat.toml").read_text()
    period_s = period_ms / 1000
    text = text.replace('name = "jiwy_ethercat"', f'name = "{name}"')
    text = text.replace('interface = "ecm0"', f'interface = "{master}"')
    text = text.replace('emulator_interface = "ecs0"', f'emulator_interface = "{slave}"')
    text = text.replace("period_ns = 1_000_000", f"period_ns = {round(period_ms * 1_000_000)}")
    text = text.replace("period_s = 0.001", f"period_s = {period_s}")
    text = text.replace("cycle_s = 0.001", f"cycle_s = {period_s}")
    text = re.sub(r"timeout_us = \d+", f"timeout_us = {int(period_ms * 900)}", text)
    if drives > 2:
        pan = text[text.index("[[devices.gimbal.joints]]"):text.index('[[devices.gimbal.joints]]\nname = "tilt"')]
        extra = "".join(pan.replace('name = "pan"', f'name = "j{k}"') for k in range(3, drives + 1))
        at = text.index("[devices.gimbal.limits.pan_target_position_rad]")
        text = text[:at] + extra + text[at:]
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new)
    path = folder / f"{name}.toml"
    path.write_text(text)
    return path


def start_emulator(app: Path, log: Path, *args: str) -> subprocess.Popen[str]:
    """``rtloop io emulate ethercat --app APP`` on the app's emulator interface, ready to answer."""
    process = subprocess.Popen([sys.executable, "-m", "rtloop", "io", "emulate", "ethercat", "--app", str(app),
                                "--log", str(log), "--priority", "60", *args],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 30
    while not (log.exists() and "emulating" in log.read_text()):
        if process.poll() is not None:
            pytest.fail(f"the emulator ended (exit {process.returncode}): {process.communicate()[1]}")
        if time.monotonic() > deadline:
            pytest.fail("the emulator did not start within 30 s")
        time.sleep(0.05)
    return process


def stop(process: subprocess.Popen[str]) -> str:
    """End the emulator (SIGTERM); what it wrote on standard error."""
    if process.poll() is None:
        process.terminate()
    try:
        _, stderr = process.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        process.kill()
        _, stderr = process.communicate()
    return stderr or ""
