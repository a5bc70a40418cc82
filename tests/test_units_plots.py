"""Units of signals and plot groups: declared by runnables, FMUs and the app; inferred setpoint pairs;
carried into signals.json, run.mcap and ``rtloop.load``."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

import rtloop
from rt_test_runnables import Gain, PiController
from rtloop.app.appfile import load_app
from rtloop.errors import AppError, AppFileError

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
MS = 1_000_000


class Motor(rtloop.Runnable):
    """A first-order speed response to a voltage; declares its units in one line each."""

    n_inputs, n_outputs = 1, 2
    input_names = ("voltage",)
    output_names = ("omega", "current")
    input_units = ("V",)
    output_units = ("rad/s", "A")

    def prerun(self) -> None:
        self.omega = 0.0

    def step(self, u, y) -> None:
        self.omega += 0.05 * (u[0] - self.omega)
        y[0], y[1] = self.omega, 0.1 * (u[0] - self.omega)


def motor_app(name: str) -> tuple[rtloop.App, rtloop.app.builder.TaskSpec, rtloop.app.builder.TaskSpec]:
    app = rtloop.App(name)
    motor = app.add_task("motor", Motor(), period_ns=MS, policy="other")
    pi = app.add_task("pi", PiController(1, kp=1.0, ki=2.0), period_ns=MS, policy="other")
    app.connect(motor.y[0], pi.u[0])
    app.connect(pi.y[0], motor.u[0])
    app.port("setpoint", to=pi.u[1], initial=[1.0])
    app.record(motor.y, pi.y, pi.u[1])
    return app, motor, pi


def test_units_and_an_inferred_setpoint_pair_reach_the_recording_and_load(tmp_path: Path) -> None:
    app, _, _ = motor_app("units_inferred")
    app.set_units("pi", {"y[0]": "V", "u[1]": "rad/s"})
    rtloop.simulate(app, 0.2, tmp_path / "sim")
    run = rtloop.load(tmp_path / "sim")
    assert run.signals.units == {"motor.omega": "rad/s", "motor.current": "A", "pi.y[0]": "V", "pi.u[1]": "rad/s"}
    [plot] = run.signals.plots
    assert plot.inferred and plot.signals == ("motor.omega", "pi.u[1]") and plot.setpoint == "pi.u[1]"
    # signals.csv is unchanged: a plain header any CSV tool reads
    header = (tmp_path / "sim" / "signals.csv").read_text().splitlines()[0]
    assert header == "t_s,motor.omega,motor.current,pi.y[0],pi.u[1]"


def test_units_are_in_run_mcap_metadata(tmp_path: Path) -> None:
    pytest.importorskip("mcap", reason="run.mcap needs the ros extra")
    from mcap.reader import make_reader

    app, _, _ = motor_app("units_mcap")
    rtloop.simulate(app, 0.05, tmp_path / "sim")
    with open(tmp_path / "sim" / "run.mcap", "rb") as file:
        metadata = {m.name: dict(m.metadata) for m in make_reader(file).iter_metadata()}
    assert json.loads(metadata["rtloop"]["units"]) == {"motor.omega": "rad/s", "motor.current": "A"}


def test_declared_plots_and_units_from_an_app_file(tmp_path: Path) -> None:
    (tmp_path / "units_models.py").write_text(
        "from rtloop import Runnable\n"
        "class Source(Runnable):\n"
        "    n_inputs, n_outputs = 0, 2\n"
        "    output_names = ('angle', 'rate')\n"
        "    def step(self, u, y):\n"
        "        y[0] = self.tick.time_s\n"
        "        y[1] = 1.0\n")
    app_file = tmp_path / "units_file.toml"
    app_file.write_text(
        'name = "units_file"\n'
        "[tasks.src]\n"
        'runnable = "units_models:Source"\nperiod_ns = 1_000_000\npolicy = "other"\n'
        'units = { angle = "rad", "y[1]" = "rad/s" }\n'
        "[record]\nsignals = ['src.y']\n"
        "[[plot]]\ntitle = 'both'\nsignals = ['src.angle', 'src.rate']\n")
    app = load_app(app_file)
    assert app.unit_overrides == {("src", "y", 0): "rad", ("src", "y", 1): "rad/s"}
    rtloop.simulate(app, 0.05, tmp_path / "sim")
    run = rtloop.load(tmp_path / "sim")
    assert run.signals.units == {"src.angle": "rad", "src.rate": "rad/s"}
    assert [(p.title, p.signals, p.inferred) for p in run.signals.plots] == [("both", ("src.angle", "src.rate"), False)]


@pytest.mark.parametrize(("extra", "key", "words"), [
    ("[[plot]]\nsignals = ['src.nope']\n", "plot[0]", "not a signal"),
    ("[[plot]]\nsignals = []\n", "plot[0].signals", "expected signal names"),
    ("[[plot]]\nsignals = ['src.y']\ncolour = 'red'\n", "plot[0].colour", "unknown key"),
    ("[tasks.src.units]\n'y[0]' = 'a,b'\n", "tasks.src", "unit"),
    ("[tasks.src.units]\n'y[7]' = 'rad'\n", "tasks.src", "out of range"),
])
def test_bad_plots_and_units_name_the_key(tmp_path: Path, extra: str, key: str, words: str) -> None:
    app_file = tmp_path / "bad.toml"
    app_file.write_text('name = "bad"\n[tasks.src]\nrunnable = "rt_test_runnables:Counter"\nperiod_ns = 1_000_000\n'
                        + extra)
    with pytest.raises(AppFileError) as error:
        load_app(app_file)
    assert key in str(error.value) and words in str(error.value)


def test_builder_checks(tmp_path: Path) -> None:
    app, motor, _ = motor_app("units_checks")
    with pytest.raises(AppError, match="unknown task"):
        app.set_units("nope", {"y[0]": "V"})
    with pytest.raises(AppError, match="unit"):
        app.set_units("motor", {"omega": 3})
    with pytest.raises(AppError, match="at least one signal"):
        app.plot()
    spec = app.plot(motor.y[0], title="speed")
    assert spec.title == "speed" and spec in app.plots


def test_a_port_that_is_no_setpoint_is_not_paired(tmp_path: Path) -> None:
    app = rtloop.App("units_nosetpoint")
    a = app.add_task("a", Gain(1), period_ns=MS, policy="other")
    b = app.add_task("b", PiController(1), period_ns=MS, policy="other")
    app.connect(a.y[0], b.u[0])
    app.port("load", to=b.u[1])  # a disturbance, not a setpoint
    app.record(a.y, b.u)
    rtloop.simulate(app, 0.02, tmp_path / "sim")
    assert rtloop.load(tmp_path / "sim").signals.plots == ()


def test_the_examples_declare_units_and_pair_setpoints(tmp_path: Path) -> None:
    sys.path.insert(0, str(EXAMPLES / "dcmotor"))
    try:
        app = load_app(EXAMPLES / "dcmotor" / "dcmotor.toml")
        rtloop.simulate(app, 0.3, tmp_path / "dc")
    finally:
        sys.path.remove(str(EXAMPLES / "dcmotor"))
    run = rtloop.load(tmp_path / "dc")
    assert run.signals.units["plant.speed_rad_s"] == "rad/s" and run.signals.units["plant.current_A"] == "A"
    assert run.signals.units["pi.kp"] == "V·s/rad" and run.signals.units["pi.ki"] == "V/rad"  # the live gains
    assert [(p.signals, p.setpoint) for p in run.signals.plots] == [
        (("plant.speed_rad_s", "pi.setpoint_rad_s"), "pi.setpoint_rad_s")]
    assert np.isfinite(run.signals["plant.speed_rad_s"]).all()


def test_a_setpoint_beside_a_device_reading_is_paired(tmp_path: Path) -> None:
    """The serial DC motor: the speed comes from a device, not a task; the setpoint port is drawn
    over the reading as the PI takes it in (a task input, recorded), and a sweep finds the pair."""
    app = load_app(EXAMPLES / "dcmotor_serial" / "dcmotor_serial.toml")
    rtloop.simulate(app, 0.3, tmp_path / "dc")
    run = rtloop.load(tmp_path / "dc")
    assert [(p.signals, p.setpoint) for p in run.signals.plots] == [
        (("pi.speed_rad_s", "pi.setpoint_rad_s"), "pi.setpoint_rad_s"),
        (("pi.voltage_V", "motor.voltage_V"), "pi.voltage_V")]  # what the motor was sent, over what the PI asked
    assert run.signals.plots[1].limits and run.signals.units["motor.voltage_V"] == "V"  # the PI's output's unit
    assert run.signals.units["pi.speed_rad_s"] == "rad/s"


def test_fmu_units_are_the_model_descriptions(tmp_path: Path) -> None:
    pytest.importorskip("fmpy", reason="FMUs need the fmu extra")
    from rtloop.models.fmu import FmuModel
    from rtloop.models.fmu_build import build_fmu

    fmu = build_fmu(EXAMPLES / "jiwy" / "models" / "fmu", tmp_path / "JiwyPlant.fmu")
    model = FmuModel(fmu)
    assert model.output_units == ("rad", "rad") and model.input_units == ("", "")
    from rtloop.models.base import ModelRunnable

    assert ModelRunnable(model).output_units == ("rad", "rad")


@pytest.mark.parametrize("example", ["jiwy_dynamixel/jiwy_dynamixel.toml", "so100_feetech/so100_feetech.toml"])
def test_the_servo_examples_give_their_live_parameters_units(example: str) -> None:
    # the report drew aim.speed_rad_s and aim.accel_rad_s2 on an axis "value (no unit declared)"
    from rtloop.record.sidecar import sidecar_content

    units = {name: column["unit"] for name, column in sidecar_content(load_app(EXAMPLES / example))["columns"].items()}
    named = {name: unit for name, unit in units.items() if name.endswith(("_rad", "_rad_s", "_rad_s2", "_s"))}
    assert named and all(named.values()), named
    assert units.get("aim.speed_rad_s", "rad/s") == "rad/s" and units.get("aim.accel_rad_s2", "rad/s²") == "rad/s²"
