"""An FMI 3 co-simulation FMU that declares hasEventMode="true" and refuses ``eventModeUsed`` at
instantiate (issue 30, defect 8): rtloop instantiates it without Event Mode (FMI 3.0 leaves the choice
to the importer) and says so; an FMU that cannot start is one line naming it and its own message.

The FMU is built here from tests/fmus/noeventmode (y' = k·u, Euler; k ≤ 0 refused at initialisation).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import unique_name
from rtloop.models import ModelError, load_model

TESTS = Path(__file__).parent
PERIOD_NS = 10_000_000


@pytest.fixture(scope="module")
def fmu(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("gcc") is None:
        pytest.skip("gcc not installed: cannot build the test FMU")
    from rtloop.models.fmu_build import build_fmu

    return build_fmu(TESTS / "fmus" / "noeventmode", tmp_path_factory.mktemp("fmu") / "NoEventMode.fmu")


def test_a_refused_event_mode_falls_back_says_so_and_equals_fmpy(fmu: Path) -> None:
    from fmpy import simulate_fmu

    runnable = load_model(f"fmu:{fmu}", inputs=["u"])
    runnable.check_period(PERIOD_NS)
    runnable.prerun()
    assert runnable.model.start_notes == [
        "FMU NoEventMode (NoEventMode.fmu) declares Event Mode but refused it at instantiate; the FMU said: "
        "[Error] Event Mode is not supported: it runs without Event Mode, handling its events inside each step "
        "(FMI 3.0 allows it)"]
    u, y, ours = np.array([1.5]), np.zeros(1), []
    for _ in range(20):
        runnable.step(u, y)
        ours.append(y[0])
    runnable.postrun()
    signal = np.array([(0.0, 1.5)], dtype=[("time", np.float64), ("u", np.float64)])
    theirs = simulate_fmu(str(fmu), stop_time=0.2, output_interval=0.01, input=signal, output=["y"])
    assert ours == pytest.approx(list(theirs["y"][1:21]), rel=0, abs=1e-12)
    assert ours[-1] == pytest.approx(2.0 * 1.5 * 0.2)


def _app_file(tmp_path: Path, fmu: Path, k: float) -> Path:
    path = tmp_path / "noeventmode.toml"
    path.write_text(f'name = "{unique_name("noeventmode")}"\n[tasks.m]\nmodel = "fmu:{fmu}"\n'
                    f"period_ns = {PERIOD_NS}\nparameters = {{ k = {k} }}\n[record]\nsignals = ['m.y']\n")
    return path


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rtloop", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("command", ["run", "simulate"])
def test_it_starts_and_the_summary_says_event_mode_was_refused(fmu: Path, tmp_path: Path, command: str) -> None:
    done = _cli(command, str(_app_file(tmp_path, fmu, 2.0)), "--duration", "0.2", "--out", str(tmp_path / "o"), "-q")
    assert done.returncode == 0, done.stderr
    notes = json.loads((tmp_path / "o" / "summary.json").read_text())["notes"]
    assert any("FMU NoEventMode (NoEventMode.fmu) declares Event Mode but refused it at instantiate" in note
               for note in notes), notes


@pytest.mark.parametrize("command", ["run", "simulate"])
def test_an_fmu_that_cannot_start_is_one_line_with_its_own_message(fmu: Path, tmp_path: Path, command: str) -> None:
    done = _cli(command, str(_app_file(tmp_path, fmu, -1.0)), "--duration", "0.2", "--out", str(tmp_path / "o"))
    assert done.returncode == 1, done.stderr
    lines = [line for line in done.stderr.splitlines()  # (and where what was recorded is, as after any failure)
             if line.strip() and not line.startswith(("WARNING", f"rtloop {command}: everything recorded"))]
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert f"FMU {str(fmu)!r} failed to start" in lines[0] and "the FMU said: [Error] k must be positive, got -1" \
        in lines[0], lines[0]


def test_the_fmus_message_is_in_the_error_in_python_too(fmu: Path) -> None:
    runnable = load_model(f"fmu:{fmu}", parameters={"k": 0.0})
    runnable.check_period(PERIOD_NS)
    with pytest.raises(ModelError, match=r"the FMU said: \[Error\] k must be positive"):
        runnable.prerun()
