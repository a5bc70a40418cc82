"""Devices: the declaration (app file and builder), the settings schema, the command guard."""

from __future__ import annotations

import math
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from device_test_drivers import LogDevice, MirrorTwin
from io_guest_devices import bytes_grown
from rtloop import App, Runnable
from rtloop.app.appfile import load_app
from rtloop.errors import AppError, AppFileError, DeviceError, DeviceFault
from rtloop.io.device import KINDS, CommandLimit, Device, build_device, device_class
from rtloop.io.limits import CommandGuard

DRIVER = "device_test_drivers:LogDevice"
LIMIT = {"min": -1.0, "max": 1.0, "safe": 0.0}


class PI(Runnable):
    n_inputs = 2
    n_outputs = 1

    def step(self, u, y) -> None:
        y[0] = u[0] - u[1]


def _app(tmp_path: Path, **options) -> tuple[App, object]:
    app = App("devices_unit")
    app.add_task("ctl", PI(), period_ns=1_000_000)
    motor = app.add_device("motor", DRIVER, task="ctl", log=str(tmp_path / "log"),
                           limits={"c0": LIMIT}, **options)
    return app, motor


def test_a_device_is_wired_to_its_task_like_a_task(tmp_path: Path) -> None:
    app, motor = _app(tmp_path)
    app.connect(motor.y[0], app.tasks["ctl"].u[1])
    app.connect(app.tasks["ctl"].y[0], motor.u[0])
    assert [str(c.source) for c in app.device_links] == ["motor.y[0]", "ctl.y[0]"]
    assert app.connections == []  # no shared memory: the device lives in ctl's process
    assert app.devices["motor"].limits == (CommandLimit(-1.0, 1.0, 0.0),)
    app.validate()


def test_a_device_reaches_only_the_task_that_owns_it(tmp_path: Path) -> None:
    app, motor = _app(tmp_path)
    app.add_task("other", PI(), period_ns=1_000_000)
    with pytest.raises(AppError, match="wired to that task only"):
        app.connect(app.tasks["other"].y[0], motor.u[0])
    with pytest.raises(AppError, match="is a device"):
        app.record(motor.y)
    with pytest.raises(AppError, match="is a device"):
        app.port("setpoint", to=motor.u[0])


def test_a_command_has_one_writer(tmp_path: Path) -> None:
    app, motor = _app(tmp_path)
    app.connect(app.tasks["ctl"].y[0], motor.u[0])
    with pytest.raises(AppError, match="at most one writer"):
        app.connect(app.tasks["ctl"].y[0], motor.u[0])


@pytest.mark.parametrize(("options", "key", "problem"), [
    ({"colour": "red"}, "colour", "unknown setting"),
    ({"gain": "2"}, "gain", "expected a number"),
    ({"gain": math.nan}, "gain", "must be finite"),
    ({"n_commands": -1}, "n_commands", "must be ≥ 0"),
    ({"n_commands": True}, "n_commands", "expected an integer"),
    ({"io": "later"}, "io", "expected one of"),
])
def test_a_bad_setting_names_device_and_key(tmp_path: Path, options, key, problem) -> None:
    with pytest.raises(DeviceError, match=problem) as caught:
        _app(tmp_path, **options)
    assert caught.value.key == key and caught.value.device == "motor"
    assert f"devices.motor.{key}" in str(caught.value)


def test_a_missing_setting_is_named(tmp_path: Path) -> None:
    app = App("devices_unit")
    app.add_task("ctl", PI(), period_ns=1_000_000)
    with pytest.raises(DeviceError, match=r"devices\.motor\.log: missing: file every call"):
        app.add_device("motor", DRIVER, task="ctl")


@pytest.mark.parametrize(("limits", "key", "problem"), [
    ({}, "limits.c0", "every command needs min, max and a safe value"),
    ({"c0": {"min": -1, "max": 1}}, "limits.c0.safe", "missing"),
    ({"c0": {**LIMIT, "safe": 2.0}}, "limits.c0", "min ≤ safe ≤ max"),
    ({"c0": {**LIMIT, "max": math.inf}}, "limits.c0", "finite"),
    ({"c0": {**LIMIT, "rate_per_s": 0}}, "limits.c0", "rate_per_s"),
    ({"c0": {**LIMIT, "slew": 1}}, "limits.c0.slew", "unknown key"),
    ({"c0": LIMIT, "c9": LIMIT}, "limits.c9", "no such command"),
])
def test_every_command_has_checked_limits_and_a_safe_value(tmp_path: Path, limits, key, problem) -> None:
    app = App("devices_unit")
    app.add_task("ctl", PI(), period_ns=1_000_000)
    with pytest.raises(DeviceError, match=problem) as caught:
        app.add_device("motor", DRIVER, task="ctl", log=str(tmp_path / "log"), limits=limits)
    assert caught.value.key == key


def test_kinds_and_names(tmp_path: Path) -> None:
    assert set(KINDS) == {"gpio", "can", "spi", "serial", "i2c", "dynamixel", "feetech", "ethercat",
                          "canopen402"}
    with pytest.raises(DeviceError, match="expected one of"):
        device_class("usb", "d", "app.toml")
    with pytest.raises(DeviceError, match="cannot import"):
        device_class("no_such_module:Driver", "d", "app.toml")
    with pytest.raises(DeviceError, match="not an rtloop Device"):
        device_class("device_test_drivers:MirrorTwin", "d", "app.toml")
    app, _motor = _app(tmp_path)
    with pytest.raises(DeviceError, match="name is taken"):
        app.add_device("ctl", DRIVER, task="ctl", log="x")
    with pytest.raises(DeviceError, match="unknown task"):
        app.add_device("m2", DRIVER, task="nobody", log="x")
    built = build_device(LogDevice, "m3", {"log": "x"}, "<python>")
    app.add_device("m3", built, task="ctl", limits={"c0": LIMIT})
    with pytest.raises(DeviceError, match="built with the name"):
        app.add_device("m4", built, task="ctl", limits={"c0": LIMIT})


def test_a_twin_answers_with_the_device_sizes(tmp_path: Path) -> None:
    _app(tmp_path, twin=MirrorTwin(1))
    with pytest.raises(DeviceError, match=r"twin.*1 inputs and 1 outputs; the device writes 2"):
        _app(tmp_path, twin=MirrorTwin(1), n_commands=2, n_readings=1)
    with pytest.raises(DeviceError, match=r"not an rtloop\.Runnable"):
        _app(tmp_path, twin=object())


APP_FILE = """
name = "devices_file"
[tasks.ctl]
runnable = "rt_test_runnables:Noop"
period_ns = 1_000_000

[devices.motor]
kind = "device_test_drivers:LogDevice"
task = "ctl"
io = "immediate"
twin = "device_test_drivers:MirrorTwin"
twin_args = {n = 2, gain = 0.5}
log = "LOG"
n_commands = 2
n_readings = 2
[devices.motor.limits.c0]
min = -2
max = 2
safe = 0
rate_per_s = 100.0
[devices.motor.limits.c1]
min = 0
max = 1
safe = 1
"""


def test_an_app_file_declares_devices(tmp_path: Path) -> None:
    path = tmp_path / "app.toml"
    path.write_text(APP_FILE.replace("LOG", str(tmp_path / "log")))
    app = load_app(path)
    spec = app.devices["motor"]
    assert (spec.task, spec.io, spec.device.n_inputs) == ("ctl", "immediate", 2)
    assert spec.limits == (CommandLimit(-2, 2, 0, 100.0), CommandLimit(0, 1, 1))
    assert isinstance(spec.twin, MirrorTwin) and spec.twin.gain == 0.5


@pytest.mark.parametrize(("change", "message"), [
    (('n_commands = 2', 'n_comands = 2'), "devices.motor.n_comands: unknown setting"),
    (('task = "ctl"', 'task = "plant"'), "devices.motor.task: unknown task 'plant'"),
    (('task = "ctl"\n', ''), "devices.motor.task: missing"),
    (('io = "immediate"', 'io = 3'), "devices.motor.io: expected a string"),
    (('twin = "device_test_drivers:MirrorTwin"', 'twin = "nowhere:Twin"'), "devices.motor.twin: cannot import"),
    (('gain = 0.5}', 'gain = 0.5, x = 1}'), "devices.motor.twin_args: "),
    (('safe = 1\n', 'safe = 5\n'), "devices.motor.limits.c1: need min ≤ safe ≤ max"),
])
def test_a_bad_device_table_is_one_line_naming_the_key(tmp_path: Path, change, message) -> None:
    path = tmp_path / "app.toml"
    path.write_text(APP_FILE.replace("LOG", str(tmp_path / "log")).replace(*change))
    with pytest.raises((DeviceError, AppFileError)) as caught:
        load_app(path)
    assert message in str(caught.value)
    assert str(path) in str(caught.value)


def test_a_bad_device_is_exit_2_and_one_line(tmp_path: Path) -> None:
    path = tmp_path / "app.toml"
    path.write_text(APP_FILE.replace("LOG", str(tmp_path / "log")).replace("n_readings = 2", "n_readings = -2"))
    result = subprocess.run([sys.executable, "-m", "rtloop", "run", str(path), "--duration", "0.1", "--out",
                             str(tmp_path / "out")], capture_output=True, text=True, cwd=Path(__file__).parent)
    assert result.returncode == 2, result.stderr
    assert result.stderr.count("\n") == 1 and "devices.motor.n_readings: must be ≥ 0" in result.stderr
    assert not (tmp_path / "out").exists() and not (tmp_path / "log").exists()


# --- the command guard ---------------------------------------------------------------------------

def test_the_guard_clamps_then_limits_the_rate() -> None:
    guard = CommandGuard([CommandLimit(-10, 10, 0, rate_per_s=1000.0), CommandLimit(0, 1, 1)], 1_000_000,
                         ["m.u[0]", "m.u[1]"])
    assert list(guard.apply(np.array([50.0, -3.0]), "ctl", 0)) == [1.0, 0.0]  # 1000/s · 1 ms from safe 0
    assert list(guard.apply(np.array([50.0, 0.5]), "ctl", 1)) == [2.0, 0.5]
    assert list(guard.apply(np.array([-50.0, 0.5]), "ctl", 2)) == [1.0, 0.5]
    assert list(guard.safe_values()) == [0.0, 1.0]
    assert list(guard.apply(np.array([0.5, 1.0]), "ctl", 3)) == [0.5, 1.0]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_command_is_a_fault_naming_task_cycle_and_command(bad: float) -> None:
    guard = CommandGuard([CommandLimit(-1, 1, 0)] * 2, 1_000_000, ["motor.u[0] (c0)", "motor.u[1] (c1)"])
    with pytest.raises(DeviceFault, match=r"task 'ctl', cycle 7: motor.u\[1\] \(c1\): command .* is not finite"):
        guard.apply(np.array([0.0, bad]), "ctl", 7)
    assert list(guard.last) == [0.0, 0.0]  # nothing of that cycle was taken


def test_the_guard_allocates_nothing_per_cycle() -> None:
    guard = CommandGuard([CommandLimit(-1, 1, 0, 10.0)] * 4, 1_000_000, ["a", "b", "c", "d"])
    u = np.array([0.3, -5.0, 2.0, 0.1])
    for cycle in range(100):
        guard.apply(u, "ctl", cycle)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for cycle in range(10_000):
        guard.apply(u, "ctl", cycle)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = bytes_grown(before, after)
    assert grown < 4096, grown


def test_the_seam_is_abstract() -> None:
    with pytest.raises(TypeError):
        Device("x")  # type: ignore[abstract]
