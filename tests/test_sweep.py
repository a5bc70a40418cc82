"""``rtloop sweep`` / ``rtloop.sweep``: a grid of simulations in parallel, one table, runs kept for load."""

from __future__ import annotations

import csv
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import rtloop
from rtloop.app.appfile import load_app
from rtloop.cli.main import main as cli_main
from rtloop.toolbox.sweep import METRICS, grid, step_response

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
DCMOTOR = EXAMPLES / "dcmotor" / "dcmotor.toml"


@pytest.fixture
def dcmotor_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(EXAMPLES / "dcmotor"))


def test_the_table_equals_separately_run_simulations(tmp_path: Path, dcmotor_path: None) -> None:
    gains = [0.02, 0.05, 0.1]
    result = rtloop.sweep(DCMOTOR, {"pi.kp": gains, "pi.ki": [2.0, 4.0]}, duration_s=0.6, out=tmp_path / "sweep",
                          processes=2)
    assert result.signal == "plant.speed_rad_s" and result.setpoint == "pi.setpoint_rad_s"
    assert [(r["pi.kp"], r["pi.ki"]) for r in result.rows] == [(k, i) for k in gains for i in (2.0, 4.0)]
    with open(result.table, newline="") as file:
        table = list(csv.DictReader(file))
    assert len(table) == 6 and list(table[0])[:2] == ["pi.kp", "pi.ki"]
    for row, written in zip(result.rows, table, strict=True):
        assert not row["error"]
        # the same point, simulated here on its own, gives the same numbers
        app = load_app(DCMOTOR)
        app.tasks["pi"].runnable.set_parameters({"kp": row["pi.kp"], "ki": row["pi.ki"]})
        alone = tmp_path / f"alone-{row['pi.kp']}-{row['pi.ki']}"
        rtloop.simulate(app, 0.6, alone)
        mine = rtloop.load(alone).signals
        expected = step_response(mine.t_s, mine["plant.speed_rad_s"], mine["pi.setpoint_rad_s"])
        for metric in METRICS:
            assert row[metric] == pytest.approx(expected[metric], nan_ok=True), metric
            assert float(written[metric]) == pytest.approx(expected[metric], nan_ok=True), metric
        # and the sweep's run is kept, equal to it value for value
        kept = rtloop.load(row["run_dir"]).signals
        np.testing.assert_array_equal(kept.table, mine.table)
    # a larger gain rises differently: the grid really changed the parameter
    assert len({round(r["rise_time_s"], 6) for r in result.rows}) > 1


def test_step_response_of_a_known_curve() -> None:
    t = np.arange(0, 2.0, 0.001)
    setpoint = np.where(t >= 0.5, 2.0, 0.0)
    # first-order response with time constant 0.1 s after the step: rise 10–90 % = τ·ln 9
    y = np.where(t >= 0.5, 2.0 * (1 - np.exp(-(t - 0.5) / 0.1)), 0.0)
    metrics = step_response(t, y, setpoint)
    assert metrics["rise_time_s"] == pytest.approx(0.1 * math.log(9), abs=2e-3)
    assert metrics["overshoot_pct"] == 0.0
    assert metrics["settling_time_s"] == pytest.approx(0.1 * math.log(50), abs=2e-3)
    assert metrics["steady_state_error"] == pytest.approx(0.0, abs=1e-5)
    overshooting = np.where(t >= 0.5, 2.0 + 0.5 * np.exp(-(t - 0.5) / 0.2) * np.sin(20 * (t - 0.5)), 0.0)
    assert step_response(t, overshooting, setpoint)["overshoot_pct"] > 5
    assert all(math.isnan(v) for v in step_response(t, y, np.zeros_like(t)).values())  # no step


def test_cli_table_and_bad_input(tmp_path: Path, dcmotor_path: None, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["sweep", str(DCMOTOR), "--param", "pi.kp=0.02:0.1:2", "--duration", "0.3",
                     "--out", str(tmp_path / "s"), "--processes", "1"]) == 0
    out = capsys.readouterr().out
    assert "step of plant.speed_rad_s" in out and "overshoot" in out
    assert "ss error [rad/s]" in out  # the steady-state error has the measured signal's unit
    assert (tmp_path / "s" / "sweep.csv").is_file() and (tmp_path / "s" / "0" / "signals.csv").is_file()
    again = ["sweep", str(DCMOTOR), "--param", "pi.kp=0.02:0.1:2", "--duration", "0.3", "--out", str(tmp_path / "s"),
             "--processes", "1"]
    assert cli_main(again) == 2 and "holds a sweep already" in capsys.readouterr().err  # never overwritten
    assert cli_main([*again, "--force"]) == 0
    capsys.readouterr()
    bare = ["sweep", str(DCMOTOR), "--param", "pi.kp=0.02:0.1:2", "--duration", "0.3", "--processes", "1"]
    assert cli_main([*bare, "--signal", "plant.current_A", "--out", str(tmp_path / "no_sp")]) == 0
    out = capsys.readouterr().out  # no setpoint pair: the header says what step was measured
    assert "step of plant.current_A, with no setpoint: from its first value to its last" in out, out
    assert cli_main([*bare, "--signal", "plant.speed_rad_s", "--setpoint", "pi.nothing",
                     "--out", str(tmp_path / "bad_sp")]) == 1  # every point failed
    out = capsys.readouterr().out
    assert "no signal measured" in out and "no signal 'pi.nothing' recorded (--setpoint)" in out, out
    for argv, words in (
        (["--param", "pi.kp=0.1:1"], "START:STOP:COUNT"),
        (["--param", "pi.kp=0:1:100000"], "COUNT must be 1 to 10000, got 100000"),
        (["--param", "pi.nope=0.1:1:3"], "unknown parameter 'nope'"),
        (["--param", "ghost.kp=1,2"], "no task 'ghost'"),
        (["--param", "pi.kp=nan,1"], "finite"),
        (["--param", "pi.kp=0.02:inf:3"], "need finite numbers"),
        (["--param", "pi.kp=0:1:200", "--param", "pi.ki=1:5:200"], "sweep: 40000 points; at most 10000"),
        (["--param", "pi.kp=1,2", "--processes", "100000"], "processes 100000: must be 1 to"),
        ([], "at least one parameter"),
    ):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a numpy RuntimeWarning above the one line fails too
            code = cli_main(["sweep", str(DCMOTOR), *argv, "--duration", "0.1", "--out", str(tmp_path / "bad")])
        err = capsys.readouterr().err
        assert code == 2 and words in err and "Traceback" not in err, err
        assert len(err.strip().splitlines()) == 1


def test_a_grid_too_large_is_refused_before_it_is_built(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Three parameters of 10,000 values are 1e12 points: counted, refused, never built (that took GBs)."""
    from rtloop.toolbox import sweep as sweep_module

    def no_grid(*_: object) -> None:
        raise AssertionError("the grid was built before its size was checked")

    monkeypatch.setattr(sweep_module.itertools, "product", no_grid)
    values = grid("0:1:10000")
    with pytest.raises(rtloop.AppError, match=r"^sweep: 1000000000000 points; at most 10000$"):
        rtloop.sweep(str(DCMOTOR), {"pi.kp": values, "pi.ki": values, "plant.x": values}, duration_s=0.1,
                     out=tmp_path / "never")
    assert not (tmp_path / "never").exists()


def test_grid() -> None:
    assert grid("0.1:1.0:10") == pytest.approx(np.linspace(0.1, 1.0, 10).tolist())
    assert grid("1,2.5") == [1.0, 2.5]
    assert grid("3:3:1") == [3.0]


def test_a_python_app_is_swept_too(tmp_path: Path) -> None:
    sys.path.insert(0, str(EXAMPLES / "dcmotor"))
    try:
        app = load_app(DCMOTOR)
        result = rtloop.sweep(app, {"pi.kp": [0.05, 0.08]}, duration_s=0.3, out=tmp_path / "py", processes=2)
    finally:
        sys.path.remove(str(EXAMPLES / "dcmotor"))
    assert [r["error"] for r in result.rows] == ["", ""], result.rows
    assert rtloop.load(result.rows[1]["run_dir"]).signals.rows > 0
