"""rtloop on aarch64 under qemu-user: tools/aarch64/run.sh, end to end.

It needs root, an x86-64 host that can run debootstrap and qemu-user-static, and
10 to 20 minutes, so it runs only when asked: set RTLOOP_AARCH64_ROOT to the folder of
the arm64 root (made there on the first run, reused after). See docs/raspberry-pi.md.
"""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
ROOT = os.environ.get("RTLOOP_AARCH64_ROOT")

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not ROOT,
        reason="set RTLOOP_AARCH64_ROOT=DIR to build and test rtloop in an arm64 root under qemu-user "
        "(root, 10-20 min; tools/aarch64/run.sh)",
    ),
    pytest.mark.skipif(os.geteuid() != 0, reason="tools/aarch64/run.sh needs root (debootstrap, chroot)"),
    pytest.mark.skipif(platform.machine() != "x86_64", reason="the emulation script targets x86-64 hosts"),
]


@pytest.mark.timeout(3600)
def test_rtloop_builds_tests_and_simulates_jiwy_identically_on_aarch64(tmp_path: Path) -> None:
    environment = dict(os.environ, RTLOOP_AARCH64_OUT=str(tmp_path))
    done = subprocess.run(
        ["bash", str(REPO / "tools" / "aarch64" / "run.sh"), str(ROOT)],
        env=environment, capture_output=True, text=True, cwd=REPO,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-4000:]
    checks = (tmp_path / "checks.txt").read_text()
    assert "sched_setattr_number_is_the_one_of_the_c_headers PASSED" in checks
    assert "c11_acquire_release_compile_to_aarch64_ordered_instructions PASSED" in checks
    assert "the_compiled_hot_path_orders_its_seqlocks_with_aarch64_acquire_release PASSED" in checks
    assert "compiled_modules_of_the_package_are_built_for_this_machine_and_import PASSED" in checks
    comparison = (tmp_path / "compare.txt").read_text().splitlines()
    assert sorted(line.split(":")[0] for line in comparison[1:]) == ["same 20sim", "same fmu", "same python"]
