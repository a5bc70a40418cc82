"""``rtloop io emulate ethercat --veth``: the emulator makes its veth pair and deletes it when it
ends (root; skipped otherwise); without a master's end to name, one line and exit 2."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rtloop.io.drives.veth import veth_problem


def _emulate(*args: str) -> list[str]:
    return [sys.executable, "-m", "rtloop", "io", "emulate", "ethercat", *args]


def test_the_emulator_makes_its_veth_pair_and_deletes_it_when_it_ends(tmp_path: Path) -> None:
    problem = veth_problem()
    if problem:
        pytest.skip(problem)
    tag = f"{os.getpid() % 100000:05d}"
    master, slave, log = f"evm{tag}", f"evs{tag}", tmp_path / "drives.log"
    emulator = subprocess.Popen(_emulate("--slaves", "1", "--interface", slave, "--veth", master, "--log", str(log)),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not (log.exists() and "emulating" in log.read_text()):
            assert emulator.poll() is None, emulator.communicate()[1]
            assert time.monotonic() < deadline, "the emulator did not start within 30 s"
            time.sleep(0.05)
        assert Path(f"/sys/class/net/{master}").exists() and Path(f"/sys/class/net/{slave}").exists()
    finally:
        emulator.terminate()
        _, stderr = emulator.communicate(timeout=30)
    assert emulator.returncode == 0, stderr
    assert not Path(f"/sys/class/net/{master}").exists() and not Path(f"/sys/class/net/{slave}").exists()


def test_veth_without_a_master_end_is_one_line_and_exit_2() -> None:
    done = subprocess.run(_emulate("--slaves", "1", "--interface", "evsnone", "--veth"), capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr.strip() == "rtloop io emulate: --veth: name the master's end (--veth ecm0), or give --app"
