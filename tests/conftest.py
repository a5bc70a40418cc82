from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from rtloop import rt

TESTS_DIR = Path(__file__).parent
sys.path.insert(0, str(TESTS_DIR))  # rt_test_runnables, for spawned task processes too
sys.path.insert(1, str(TESTS_DIR.parent / "examples" / "jiwy"))  # the JIWY example's plant and controller


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    capabilities = rt.probe()
    if capabilities.may_use_rt:
        return
    skip = pytest.mark.skip(reason=f"needs real-time scheduling: {capabilities.rt_reason}")
    for item in items:
        if "rt" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def rtloop_env() -> dict[str, str]:
    """Environment for running the rtloop CLI in a subprocess that finds the test runnables."""
    env = dict(os.environ)
    paths = [str(TESTS_DIR), str(TESTS_DIR.parent / "examples" / "jiwy"), env.get("PYTHONPATH", "")]
    env["PYTHONPATH"] = os.pathsep.join(paths).rstrip(os.pathsep)
    return env


def other_cpu() -> int:
    """A CPU to pin test tasks to: the last one."""
    return max(os.sched_getaffinity(0))


def find_cyclonedds_cli() -> str | None:
    """The ``cyclonedds`` command: beside this Python first (a venv's scripts are not on sudo's PATH)."""
    import shutil

    beside_python = Path(sys.executable).parent / "cyclonedds"
    return str(beside_python) if beside_python.exists() else shutil.which("cyclonedds")


@pytest.fixture(params=["c", "python"])
def hot_path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run the test under the compiled hot path and under its Python twin (task processes inherit it)."""
    from rtloop.ipc import hotpath

    if request.param == "c":
        monkeypatch.delenv(hotpath.PURE_PYTHON_ENV, raising=False)
        if not hotpath.c_built():
            pytest.skip(f"the C hot path is not available: {hotpath.why_python()}")
    else:
        monkeypatch.setenv(hotpath.PURE_PYTHON_ENV, "1")
    return request.param
