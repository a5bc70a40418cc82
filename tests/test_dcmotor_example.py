"""The DC motor + PI example (examples/dcmotor): it simulates, follows its profile, and its
PI's live parameters work as documented (app file, ports, before and during a run)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

import rtloop
from rtloop.app.appfile import load_app
from rtloop.app.builder import parse_signal
from rtloop.app.modules import load_module_file
from rtloop.errors import AppFileError, RtloopError

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "dcmotor"


def _signals(path: Path) -> list[dict[str, float]]:
    with open(path / "signals.csv", newline="") as file:
        return [{key: float(value) for key, value in row.items()} for row in csv.DictReader(file)]


def _at(rows: list[dict[str, float]], t_s: float) -> dict[str, float]:
    return next(row for row in rows if row["t_s"] >= t_s - 1e-9)


def test_the_motor_follows_the_speed_profile_with_plausible_current_and_voltage(tmp_path: Path) -> None:
    app = load_app(EXAMPLE / "dcmotor.toml")
    rtloop.simulate(app, 2.5, tmp_path / "sim")
    rows = _signals(tmp_path / "sim")
    names = {"plant.speed_rad_s", "plant.current_A", "pi.voltage_V", "pi.setpoint_rad_s", "pi.kp", "pi.ki"}
    assert names <= set(rows[0])
    for t_s, setpoint in ((0.55, 150.0), (1.15, 250.0), (1.75, 100.0), (2.45, 0.0)):  # end of each profile row
        row = _at(rows, t_s)
        assert row["pi.setpoint_rad_s"] == setpoint
        assert abs(row["plant.speed_rad_s"] - setpoint) < 0.5, (t_s, row)
    assert _at(rows, 0.099)["plant.speed_rad_s"] == 0.0  # at rest until the first step
    peak_current_A = max(abs(row["plant.current_A"]) for row in rows)
    assert 1.0 < peak_current_A < 12.0  # a few amperes, below the stall current
    assert all(-24.0 <= row["pi.voltage_V"] <= 24.0 for row in rows)
    assert all(row["pi.kp"] == 0.05 and row["pi.ki"] == 3.0 for row in rows)


def test_gains_set_in_the_app_file_reach_the_step(tmp_path: Path) -> None:
    text = (EXAMPLE / "dcmotor.toml").read_text().replace("parameters = { kp = 0.05, ki = 3.0 }",
                                                          "parameters = { kp = 0.2 }")
    (tmp_path / "app.toml").write_text(text)
    for name in ("dcmotor.py",):
        (tmp_path / name).write_text((EXAMPLE / name).read_text())
    (tmp_path / "profiles").mkdir()
    (tmp_path / "profiles" / "speed_steps.csv").write_text((EXAMPLE / "profiles" / "speed_steps.csv").read_text())
    app = load_app(tmp_path / "app.toml")
    assert app.tasks["pi"].runnable.kp == 0.2 and app.tasks["pi"].runnable.ki == 3.0
    rtloop.simulate(app, 0.2, tmp_path / "sim")
    rows = _signals(tmp_path / "sim")
    assert {row["pi.kp"] for row in rows} == {0.2}
    first = _at(rows, 0.101)  # the first tick that sees the step to 150 rad/s: all of it is kp·error
    assert first["pi.voltage_V"] == pytest.approx(min(0.2 * 150.0 + 3.0 * 150.0 * 0.001, 24.0))


def test_gains_written_while_running_take_effect_at_a_release(tmp_path: Path) -> None:
    example = load_module_file("dcmotor", EXAMPLE / "dcmotor.py")
    app = rtloop.App("dcmotor_live")
    plant = app.add_task("plant", example.DcMotor(), period_ns=1_000_000)
    pi = app.add_task("pi", example.PiSpeed(), period_ns=1_000_000)
    app.connect(plant.y[0], pi.u[0])
    app.connect(pi.y[0], plant.u[0])
    app.port("setpoint", to=pi.u[1], initial=[100.0])
    app.port("gains", to=pi.u[2:4])
    app.record(pi.y, pi.u)
    # The run took kp = 0 and ki = 0 at cycle 50: from there on the PI holds its integral.
    writes = {("pi", 50): [("gains", [0.0, 0.0])]}
    rtloop.simulate(app, 0.1, tmp_path / "sim", port_writes=writes)
    rows = _signals(tmp_path / "sim")
    assert _at(rows, 0.049)["pi.kp"] == 0.05 and _at(rows, 0.049)["pi.voltage_V"] != 0.0
    late = [row for row in rows if row["t_s"] >= 0.051]
    assert late and all(row["pi.kp"] == 0.0 and row["pi.ki"] == 0.0 for row in late)
    assert len({row["pi.voltage_V"] for row in late}) == 1
    assert _at(rows, 0.050)["pi.voltage_V"] != late[0]["pi.voltage_V"]  # the proportional part went at 0.050


def test_the_examples_ports_into_actuators_refuse_what_would_make_them_dangerous() -> None:
    from rtloop.ipc.ports import port_range
    from rtloop.ipc.values import validate_values

    def check(app: rtloop.App, port: str, values: list[float]) -> None:
        registered = {"range": [list(b) if isinstance(b, tuple) else b for b in app.ports[port].value_range]}
        validate_values(values, len(values), where=port, value_range=port_range(registered))

    dcmotor = load_app(EXAMPLE / "dcmotor.toml")
    check(dcmotor, "gains", [0.08, 4.0])  # the README's retune
    for bad in ([1e308, 4.0], [1.0, 3.0], [0.05, 1e9], [-0.05, 3.0]):  # kp = 1 already makes ±24 V bang-bang
        with pytest.raises(ValueError, match="outside its range"):
            check(dcmotor, "gains", bad)
    jiwy = load_app(EXAMPLE.parent / "jiwy" / "jiwy.toml")
    check(jiwy, "setpoint", [0.5, 0.3])
    with pytest.raises(ValueError, match="outside its range"):
        check(jiwy, "setpoint", [1e308, 0.0])


def test_live_parameters_are_one_line_on_a_runnable_and_become_named_inputs() -> None:
    class Gain(rtloop.Runnable):
        n_inputs, n_outputs = 1, 1
        parameters = {"k": 2.0}  # noqa: RUF012

        def step(self, u, y) -> None:
            y[0] = self.k * u[0]

    gain = Gain()
    assert gain.k == 2.0
    gain.k = 3.0
    assert gain.k == 3.0 and Gain().k == 2.0  # each instance its own values; the class keeps the default
    app = rtloop.App("gain_params")
    task = app.add_task("gain", gain, period_ns=1_000_000)
    assert task.u.length == 2 and gain.input_names == ("", "k") and gain.input_start_values == (0.0, 3.0)
    assert parse_signal("gain.k", app, "test") == task.u[1]  # a port can write it: to = "gain.k"
    gain.k = 4.0  # before the run, after add_task: the run starts from it
    assert gain.input_start_values == (0.0, 4.0)


@pytest.mark.parametrize("bad", ['{"tick": 1.0}', '{"_k": 1.0}', '{"k": "fast"}', '["k"]', '{"k": float("nan")}'])
def test_a_parameter_that_cannot_work_is_refused_when_the_class_is_defined(bad: str) -> None:
    with pytest.raises(TypeError, match="parameter"):
        exec(f"class Bad(rtloop.Runnable):\n    parameters = {bad}\n    def step(self, u, y): pass",
             {"rtloop": rtloop})


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_a_parameter_that_is_not_finite_is_refused_when_the_app_file_loads(tmp_path: Path, bad: str) -> None:
    text = (EXAMPLE / "dcmotor.toml").read_text().replace("parameters = { kp = 0.05, ki = 3.0 }",
                                                          f"parameters = {{ kp = 0.05, ki = {bad} }}")
    assert bad in text
    (tmp_path / "app.toml").write_text(text)
    (tmp_path / "dcmotor.py").write_text((EXAMPLE / "dcmotor.py").read_text())
    with pytest.raises(AppFileError, match=rf"app\.toml: tasks\.pi\.parameters\.ki: {bad} is not a finite number"):
        load_app(tmp_path / "app.toml")
    text = (EXAMPLE / "dcmotor.toml").read_text().replace('to = "pi.u[2:4]"\n',
                                                          f'to = "pi.u[2:4]"\ninitial = [0.05, {bad}]\n')
    (tmp_path / "app.toml").write_text(text)
    with pytest.raises(AppFileError, match=r"ports\.gains: port 'gains': initial .* holds NaN or inf"):
        load_app(tmp_path / "app.toml")  # a port's initial values too: the task reads them at cycle 0
    pi = load_module_file("dcmotor", EXAMPLE / "dcmotor.py").PiSpeed()
    from rtloop.models.base import apply_parameters

    with pytest.raises(RtloopError, match="not a finite number"):  # the same check from Python (and sweep)
        apply_parameters(pi, {"kp": float(bad)}, "pi")


def test_parameters_on_a_runnable_that_declares_none_say_how_to_declare_them(tmp_path: Path) -> None:
    (tmp_path / "plain_pi.py").write_text(
        "from rtloop import Runnable\n"
        "class Pi(Runnable):\n    n_inputs, n_outputs = 2, 1\n    def step(self, u, y):\n        y[0] = u[0]\n")
    (tmp_path / "app.toml").write_text(
        'name = "plain_pi"\n[tasks.pi]\nrunnable = "plain_pi:Pi"\nparameters = { kp = 50.0 }\nperiod_ns = 1_000_000\n')
    with pytest.raises(AppFileError) as caught:
        load_app(tmp_path / "app.toml")
    message = str(caught.value)
    assert "declares no parameters" in message and 'parameters = {"kp": 0.0}' in message


def test_a_signal_recorded_twice_is_one_column(tmp_path: Path) -> None:
    app = load_app(EXAMPLE / "dcmotor.toml")
    app.record(app.tasks["plant"].y, app.tasks["pi"].u[1])  # both recorded already, by name or by index
    rtloop.simulate(app, 0.01, tmp_path / "sim")
    header = (tmp_path / "sim" / "signals.csv").read_text().splitlines()[0].split(",")
    assert len(header) == len(set(header))
    assert header.count("plant.speed_rad_s") == 1 and header.count("pi.setpoint_rad_s") == 1
