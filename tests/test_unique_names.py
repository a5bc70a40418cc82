"""The suite's own rule, checked (tests/conftest.py): an app a test runs in real time has a name
of this run's own, since a live app holds its name and other runs of the suite share the machine."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

PROBE = '''
import rtloop
from conftest import unique_name
from rt_test_runnables import Noop


def _run(name, tmp_path):
    app = rtloop.App(name)
    app.add_task("t", Noop(), period_ns=1_000_000, policy="other")
    rtloop.run(app, 0.02, tmp_path / "out")


def test_fixed(tmp_path):
    _run("fixed_name_probe", tmp_path)


def test_unique(tmp_path):
    _run(unique_name("unique_probe"), tmp_path)
'''


def test_a_test_that_runs_an_app_under_a_fixed_name_fails(tmp_path: Path, rtloop_env: dict[str, str]) -> None:
    (tmp_path / "test_probe.py").write_text(PROBE)
    result = subprocess.run([sys.executable, "-m", "pytest", "-p", "conftest", "-q", "-p", "no:cacheprovider",
                             "test_probe.py"], cwd=tmp_path, env=rtloop_env, capture_output=True, text=True,
                            timeout=300)
    # both ran; the fixed name is an error at teardown, the unique one none
    assert "2 passed, 1 error" in result.stdout and "ERROR test_probe.py::test_unique" not in result.stdout, \
        result.stdout + result.stderr
    assert "test_probe.py::test_fixed ran app 'fixed_name_probe' under a fixed name: use unique_name()" \
        in result.stdout, result.stdout
