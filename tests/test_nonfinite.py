"""A NaN or infinity crossing a connection is a fault naming task, cycle and output, unless the
connection allows it; either way the summary counts and names it (C and Python hot paths)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rtloop
from conftest import other_cpu
from rt_test_runnables import Gain
from rtloop import App, Runnable, TaskFailed
from rtloop.linux import rt

P = 1_000_000


class DividesByZeroAt(Runnable):
    """y = [cycle, 1/(cycle - at)·0 …]: y[1] turns NaN at cycle ``at`` (numpy: only a warning)."""

    n_inputs = 0
    n_outputs = 2
    output_names = ("count", "speed")

    def __init__(self, at: int) -> None:
        self.at = at

    def step(self, u, y) -> None:
        y[0] = self.tick.cycle
        y[1] = np.nan if self.tick.cycle >= self.at else 1.0


def _app(name: str, allow: bool) -> App:
    app = App(name)
    plant = app.add_task("plant", DividesByZeroAt(30), period_ns=P, priority=60, cpu=other_cpu())
    controller = app.add_task("controller", Gain(2), period_ns=P, priority=59, cpu=other_cpu())
    app.connect(plant.y[0], controller.u[0])
    app.connect(plant.y[1], controller.u[1], allow_nonfinite=allow)
    app.record(controller.y)
    return app


@pytest.mark.parametrize("mode", ["simulate", "run"])
def test_a_nan_crossing_a_connection_is_a_fault_naming_task_cycle_and_output(tmp_path: Path, hot_path, mode) -> None:
    if mode == "run" and not rt.probe().may_use_rt:
        pytest.skip("needs real-time scheduling")
    run = rtloop.simulate if mode == "simulate" else rtloop.run
    with pytest.raises(TaskFailed) as failed:
        # 5 s is a bound: the fault at cycle 30 ends the run (a 0.2 s run once ended first on a loaded
        # machine that stalled the task for most of it)
        run(_app(f"nan_fault_{mode}_{hot_path}_{os.getpid()}", allow=False), 5.0, tmp_path)
    error = failed.value
    assert error.task == "plant" and error.phase == "step"
    if mode == "simulate":
        assert error.cycle == 30
    else:  # the first cycle that ran from 30 on: a loaded machine may skip releases 30, 31, ...
        with open(tmp_path / "timing.csv") as file:
            ran = [int(row.split(",")[1]) for row in file if row.startswith("plant,")]
        assert error.cycle >= 30 and ran and max(ran) < 30, (error.cycle, ran[-3:])
    assert "plant.y[1] (speed)" in error.reason and "nan" in error.reason
    assert f"cycle {error.cycle}" in error.reason
    assert "allow_nonfinite" in error.reason  # says how to let it through
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["tasks"]["plant"]["nonfinite_values"] == 1
    with open(tmp_path / "signals.csv") as file:
        rows = list(file)[1:]
    assert not any("nan" in row.lower() for row in rows), "the NaN never crossed"


def test_a_connection_that_allows_it_lets_it_cross_and_the_summary_counts_and_names_it(tmp_path: Path,
                                                                                      hot_path) -> None:
    summary = rtloop.simulate(_app(f"nan_allowed_{hot_path}_{os.getpid()}", allow=True), 0.1, tmp_path)
    plant = summary.tasks["plant"]
    assert plant.nonfinite_values == 100 - 30
    assert "plant.y[1] (speed)" in plant.nonfinite_first and "cycle 30" in plant.nonfinite_first
    assert any("plant.y[1] (speed)" in note and "70" in note for note in summary.notes)
    with open(tmp_path / "signals.csv") as file:
        last = list(file)[-1].strip().split(",")
    assert math.isnan(float(last[2])), "allowed: controller.u[1] = NaN reached the gain"


def test_allow_nonfinite_in_the_app_file_and_a_bad_value_is_one_line(tmp_path: Path, rtloop_env) -> None:
    from rtloop.app.appfile import load_app

    text = (
        'name = "nanfile"\n'
        '[tasks.a]\nrunnable = "rt_test_runnables:Gain"\nperiod_ns = 1_000_000\n'
        '[tasks.b]\nrunnable = "rt_test_runnables:Gain"\nperiod_ns = 1_000_000\n'
        '[[connect]]\nfrom = "a.y[0]"\nto = "b.u[0]"\nallow_nonfinite = true\n'
        '[[connect]]\nfrom = "a.y[1]"\nto = "b.u[1]"\n'
    )
    path = tmp_path / "nanfile.toml"
    path.write_text(text)
    app = load_app(path)
    assert [c.allow_nonfinite for c in app.connections] == [True, False]
    path.write_text(text.replace("allow_nonfinite = true", 'allow_nonfinite = "yes"'))
    result = subprocess.run([sys.executable, "-m", "rtloop.cli", "simulate", str(path), "--duration", "0.1",
                             "--out", str(tmp_path / "out")], env=rtloop_env, capture_output=True, text=True)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "connect[0].allow_nonfinite" in result.stderr and "true or false" in result.stderr
