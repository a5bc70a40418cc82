"""The core install (``pip install rtloop``, numpy only) runs and simulates JIWY.

Each missing extra is one line naming what installs it, never a traceback. The test builds
a fresh virtual environment with the package and no extras, as a user would.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import unique_name

REPO = Path(__file__).resolve().parents[1]
JIWY = REPO / "examples" / "jiwy" / "jiwy.toml"


@pytest.fixture(scope="module")
def base_venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    venv = tmp_path_factory.mktemp("base-venv")
    # Without a pip of its own (ensurepip takes seconds): this environment's pip installs into it.
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    install = subprocess.run([sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"), "install", "-q",
                              str(REPO)], capture_output=True, text=True, timeout=600)
    if install.returncode != 0:
        pytest.skip(f"cannot install rtloop into a fresh venv here: {install.stderr.strip()[-300:]}")
    for extra in ("mcap", "matplotlib", "rich", "cyclonedds", "fmpy"):
        probe = subprocess.run([str(venv / "bin" / "python"), "-c", f"import {extra}"], capture_output=True)
        assert probe.returncode != 0, f"{extra} should not be in the base install"
    return venv


def rtloop(venv: Path, *args: str, cwd: Path, models: Path | None = None) -> subprocess.CompletedProcess[str]:
    """The base install's ``rtloop``; nothing of this checkout on its path but the ``models`` folder."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if models is not None:
        env["PYTHONPATH"] = str(models)
    return subprocess.run([str(venv / "bin" / "rtloop"), *args], capture_output=True, text=True,
                          timeout=120, cwd=cwd, env=env)


@pytest.mark.slow
@pytest.mark.parametrize("command", ["simulate", "run"])
def test_base_install_runs_jiwy(base_venv: Path, tmp_path: Path, command: str) -> None:
    out = tmp_path / command
    app_file = tmp_path / "jiwy.toml"  # under a name of this test run alone: a live app holds its name
    app_file.write_text(JIWY.read_text().replace('name = "jiwy"', f'name = "{unique_name("jiwy_base")}"', 1))
    result = rtloop(base_venv, command, str(app_file), "--duration", "0.5", "--out", str(out), "--quiet",
                    cwd=tmp_path, models=JIWY.parent)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    for name in ("summary.json", "timing.csv", "signals.csv"):
        assert (out / name).stat().st_size > 0, name
    assert not (out / "run.mcap").exists()
    summary = (out / "summary.json").read_text()
    assert "run.mcap skipped: no module 'mcap' (pip install 'rtloop[ros]')" in summary


@pytest.mark.slow
@pytest.mark.parametrize(("args", "extra"), [(("top", "--once"), "report"), (("report", "."), "report")])
def test_missing_extra_is_one_line(base_venv: Path, tmp_path: Path, args: tuple[str, ...], extra: str) -> None:
    result = rtloop(base_venv, *args, cwd=tmp_path)
    assert result.returncode == 2  # a missing optional package is bad input
    assert result.stderr.count("\n") == 1 and f"pip install 'rtloop[{extra}]'" in result.stderr, result.stderr
