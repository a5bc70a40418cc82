"""A device reading that is not finite (an ADC glitch, a CAN f32 of NaN bits, a twin's NaN) is a
fault at the read, before the task steps with it, naming task, cycle and reading; the devices get
their safe values. A controller's clamp ``min(24, max(-24, v))`` would turn NaN into full
reverse voltage. ``allow_nonfinite = true`` on the connection lets it through, as between tasks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import rtloop
from conftest import unique_name
from device_test_drivers import Echo, LogDevice, MirrorTwin, NanTwin, read_log
from rtloop import App
from rtloop.errors import DeviceFault, TaskFailed
from rtloop.io.device import CommandLimit, build_device
from rtloop.io.host import DeviceWiring, TaskDevices

PERIOD_NS = 2_000_000
LIMIT = {"min": -1e6, "max": 1e6, "safe": -7.0}


def nan_app(tmp_path: Path, name: str, *, allow_nonfinite: bool = False) -> App:
    """Task ``ctl``: y = u + 1; device ``dev`` reads back its command, NaN once the command reached 3."""
    app = App(unique_name(name))
    ctl = app.add_task("ctl", Echo(), period_ns=PERIOD_NS)
    dev = app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(tmp_path / "dev.log"),
                         nan_reading_at=3.0, twin=NanTwin(3.0), limits={"c0": LIMIT})
    app.connect(ctl.y[0], dev.u[0])
    app.connect(dev.y[0], ctl.u[0], allow_nonfinite=allow_nonfinite)
    app.record(ctl.y, ctl.u)
    return app


def test_a_nan_reading_stops_the_run_before_the_task_steps_with_it(tmp_path: Path) -> None:
    with pytest.raises(TaskFailed) as caught:
        rtloop.run(nan_app(tmp_path, "nanread_run"), 1.0, tmp_path / "out")
    # writes 0, 1, 2, 3 (LET): the command 3 written at release 3 is read back as NaN at that release
    assert "DeviceFault: task 'ctl', cycle 3: dev.y[0] (y0): reading nan is not finite" in str(caught.value)
    log = read_log(tmp_path / "dev.log")
    assert [line for line in log if line.startswith("write ")] == ["write 0.0", "write 1.0", "write 2.0", "write 3.0"]
    assert log[-3:] == ["safe -7.0", "deactivate", "close"]


def test_a_nan_reading_from_a_twin_in_simulation_too(tmp_path: Path) -> None:
    with pytest.raises(TaskFailed, match=r"cycle 3: dev\.y\[0\] \(y0\): reading nan is not finite"):
        rtloop.simulate(nan_app(tmp_path, "nanread_sim"), 1.0, tmp_path / "out")


def test_allow_nonfinite_on_the_connection_lets_the_reading_through(tmp_path: Path) -> None:
    # it crosses: Echo then computes nan + 1, and the command guard refuses that at the next release
    with pytest.raises(TaskFailed, match=r"cycle 4: dev\.u\[0\] \(c0\): command nan is not finite"):
        rtloop.simulate(nan_app(tmp_path, "nanread_allow", allow_nonfinite=True), 1.0, tmp_path / "out")


@pytest.mark.parametrize("compiled", [True, False])
def test_the_fault_is_the_same_from_c_and_python_and_names_the_reading(monkeypatch, compiled: bool) -> None:
    if compiled:
        pytest.importorskip("rtloop.io._devio", reason="the devices' C part was not built (no compiler)")
    else:
        monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
    device = build_device(LogDevice, "dev", {"log": "/dev/null", "n_readings": 3}, "app.toml")
    device.output_names = ("speed", "current", "spare")
    readings = ((slice(0, 1), slice(0, 1)), (slice(1, 3), slice(1, 3)))
    task_u, task_y = np.zeros(3), np.zeros(1)
    limits = (CommandLimit(-1.0, 1.0, 0.0),)
    devices = TaskDevices("ctl", 1_000_000, [DeviceWiring(device, "let", limits, (), readings, "app.toml",
                                                           (True, False))], task_u, task_y)
    assert (devices.slots[0].compiled_readings is not None) == compiled
    device.read = lambda y: y.__setitem__(slice(None), [np.nan, 2.0, 3.0])  # speed allowed to be NaN
    devices.at_release(0)
    assert np.isnan(task_u[0]) and list(task_u[1:]) == [2.0, 3.0]
    device.read = lambda y: y.__setitem__(slice(None), [1.0, 2.0, -np.inf])
    with pytest.raises(DeviceFault, match=r"task 'ctl', cycle 7: dev\.y\[2\] \(spare\): reading -inf is not finite"):
        devices.at_release(7)


def test_a_twin_reading_nan_is_a_twin_of_the_mirror() -> None:
    twin, mirror = NanTwin(3.0), MirrorTwin(1, 1.0)
    for command in (0.0, 2.5):
        y, z = np.zeros(1), np.zeros(1)
        twin.step(np.array([command]), y)
        mirror.step(np.array([command]), z)
        assert y[0] == z[0]
    y = np.zeros(1)
    twin.step(np.array([3.0]), y)
    assert np.isnan(y[0])
