"""Models inside apps: 20-sim exports and FMUs wired like any task; misbehaving models."""

from __future__ import annotations

import csv
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import rtloop
from conftest import other_cpu, unique_name
from rt_test_runnables import Counter, SegfaultAt
from rtloop import App, TaskFailed
from rtloop.app.appfile import load_app

JIWY = Path(__file__).parent.parent / "examples" / "jiwy"
needs_compiler = pytest.mark.skipif(shutil.which("g++") is None or shutil.which("gcc") is None,
                                    reason="needs g++ and gcc to build the 20-sim fixtures and the FMU")


def jiwy_variant(folder: Path, plant_line: str, controller_line: str) -> Path:
    """A copy of jiwy.toml and its models in ``folder``, with other plant/controller implementations."""
    if not (folder / "models").exists():
        shutil.copytree(JIWY / "models", folder / "models")
    text = (JIWY / "jiwy.toml").read_text()
    text = text.replace('runnable = "jiwy_models:JiwyPlant"', plant_line)
    text = text.replace('runnable = "jiwy_models:JiwyController"', controller_line)
    path = folder / f"jiwy-{len(list(folder.glob('*.toml')))}.toml"
    path.write_text(text)
    return path


def simulate_signals(app_file: Path, out: Path) -> list[list[str]]:
    app = load_app(app_file)
    app.feed("setpoint", JIWY / "setpoints" / "step.csv")
    rtloop.simulate(app, 2.0, out)
    with open(out / "signals.csv", newline="") as file:
        return list(csv.reader(file))


@needs_compiler
def test_jiwy_with_20sim_cpp_models_and_fmu_plant_matches_python_models(tmp_path: Path) -> None:
    from rtloop.models.fmu_build import build_fmu

    fmu = build_fmu(JIWY / "models" / "fmu", tmp_path / "JiwyPlant.fmu")
    reference = simulate_signals(JIWY / "jiwy.toml", tmp_path / "python")
    variants = {
        "20sim": jiwy_variant(tmp_path, 'model = "20sim:models/Plant"', 'model = "20sim:models/Controller"'),
        "fmu": jiwy_variant(tmp_path, f'model = "fmu:{fmu}"', 'runnable = "jiwy_models:JiwyController"'),
    }
    for name, path in variants.items():
        rows = simulate_signals(path, tmp_path / name)
        # model variable names as columns; the initial outputs at t = 0, then tick k's outputs at (k+1)·P
        assert rows[0] == reference[0] and len(rows) == len(reference) == 2002
        assert rows[0][1:3] == ["plant.AnglePan", "plant.AngleTilt"] and rows[1][0] == "0.0"
        worst = max(abs(float(a) - float(b)) for ra, rb in zip(rows[1:], reference[1:], strict=True)
                    for a, b in zip(ra[1:5], rb[1:5], strict=True))
        assert worst <= 1e-9, f"{name} differs from the Python models by {worst} rad"
    # the thesis's functionality test: a 0.5 / 0.3 rad step at 0.5 s settles within about 1 s, overshooting
    pan = [float(row[1]) for row in reference[1:]]
    tilt = [float(row[2]) for row in reference[1:]]
    assert max(pan) > 0.52 and max(tilt) > 0.31, "the JIWY step response overshoots"
    assert abs(pan[1501] - 0.5) < 0.005 and abs(tilt[1501] - 0.3) < 0.005, "settled 1 s after the step"


@needs_compiler
def test_a_20sim_folder_that_does_not_compile_names_the_folder_and_shows_the_compiler(tmp_path: Path) -> None:
    broken = tmp_path / "Broken"
    shutil.copytree(JIWY / "models" / "Plant", broken)
    source = broken / "Plant.cpp"
    source.write_text(source.read_text().replace(";", " oops;", 1))
    app_file = tmp_path / "broken.toml"
    app_file.write_text(f'name = "broken"\n[tasks.plant]\nmodel = "20sim:{broken}"\nperiod_ns = 1_000_000\n')
    result = subprocess.run([sys.executable, "-m", "rtloop.cli", "simulate", str(app_file), "--duration", "0.1",
                             "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert result.returncode == 2
    assert "tasks.plant.model" in result.stderr and str(broken) in result.stderr
    assert "oops" in result.stderr and "error" in result.stderr  # the compiler's own words


def test_model_info_cli_lists_signals_and_step_size() -> None:
    result = subprocess.run([sys.executable, "-m", "rtloop.cli", "model", "info", str(JIWY / "models" / "Plant")],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "AnglePan" in result.stdout and "SteeringTilt" in result.stdout and "1 ms" in result.stdout


@pytest.mark.rt
def test_a_model_that_segfaults_kills_only_its_task_and_is_reported(tmp_path: Path) -> None:
    app = App(unique_name("segfault"))
    crash = app.add_task("crash", SegfaultAt(cycle=200), period_ns=1_000_000, cpu=other_cpu())
    app.add_task("other", Counter(), period_ns=1_000_000, cpu=other_cpu(), priority=70)
    app.record(crash.y)
    with pytest.raises(TaskFailed, match="SIGSEGV") as caught:
        rtloop.run(app, 5, tmp_path)
    assert caught.value.task == "crash" and caught.value.phase == "step"
    with open(tmp_path / "signals.csv", newline="") as file:
        rows = list(csv.reader(file))
    last_computed = float(rows[-1][1])
    assert last_computed >= 190  # what it computed before dying is kept
    # the cycle it died in, as the supervisor saw it: 200 unless a loaded machine skipped releases
    assert caught.value.cycle is not None and 195 <= caught.value.cycle <= last_computed + 10
    assert (tmp_path / "summary.json").exists()
