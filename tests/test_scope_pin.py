"""The scope pin is a device hook (io/host.py ScopePin), not part of the hot path: the task's devices
toggle it first thing at every release, or hold it high for exactly the step. The edges on real
gpio-sim lines are checked in the guest (tests/test_io_scope_estop.py); here, the ioctls themselves."""

from __future__ import annotations

import errno

import numpy as np
import pytest

from device_test_drivers import LogDevice  # type: ignore[import-not-found]
from rtloop.errors import LibcError
from rtloop.io import host
from rtloop.io.device import CommandLimit, build_device
from rtloop.io.host import DeviceWiring, TaskDevices
from rtloop.io.kernel import GPIO_V2_LINE_SET_VALUES_IOCTL, GPIO_V2_LINE_VALUES

BIT = 3


class PanelWithScope(LogDevice):
    """A device with a scope pin on (stand-in) line request fd 99, bit 3."""

    mode = 1

    def scope_output(self) -> tuple[int, int, int, int]:
        return 99, GPIO_V2_LINE_SET_VALUES_IOCTL, BIT, self.mode


def cycles(monkeypatch: pytest.MonkeyPatch, tmp_path, mode: int, fail: bool = False,
           raises_at: int | None = None) -> list[object]:
    """What the devices of a task do over three cycles and a stop: the scope pin's writes and the
    steps between them."""
    seen: list[object] = []

    def ioctl(fd: int, request: int, values: bytearray, name: str) -> None:
        assert (fd, request, name) == (99, GPIO_V2_LINE_SET_VALUES_IOCTL, "GPIO_V2_LINE_SET_VALUES_IOCTL")
        bits, mask = GPIO_V2_LINE_VALUES.unpack_from(values, 0)
        assert mask == 1 << BIT
        seen.append(bits >> BIT)
        if fail:
            raise LibcError("ioctl(GPIO_V2_LINE_SET_VALUES_IOCTL)", errno.EIO)

    monkeypatch.setattr(host.rt, "ioctl", ioctl)
    device = build_device(PanelWithScope, "panel", {"log": str(tmp_path / "log")}, "app.toml")
    device.mode = mode
    devices = TaskDevices("ctl", 1_000_000, [DeviceWiring(device, "let", (CommandLimit(-1.0, 1.0, 0.0),), (), ())],
                          np.zeros(1), np.zeros(1))
    devices.configure()
    devices.activate()
    for cycle in range(3):
        devices.at_release(cycle)
        seen.append("step")
        if cycle == raises_at:
            break  # the step raised: the loop goes to the stop, the pin still high
        devices.after_step(cycle)
    devices.stop()
    return seen


def test_toggle_an_edge_at_every_release(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    assert cycles(monkeypatch, tmp_path, mode=1) == [1, "step", 0, "step", 1, "step"]


def test_step_high_for_exactly_the_step_and_one_edge_each_way(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    # the stop writes nothing when the pin is low already: one rise and one fall per step, as a
    # scope and the guest's count of the pin's writes (tests/test_io_scope_estop.py) expect
    assert cycles(monkeypatch, tmp_path, mode=2) == [1, "step", 0] * 3


def test_a_step_that_raised_leaves_the_pin_high_and_the_stop_brings_it_low(monkeypatch, tmp_path) -> None:
    assert cycles(monkeypatch, tmp_path, mode=2, raises_at=1) == [1, "step", 0, 1, "step", 0]


def test_a_failed_write_of_the_scope_pin_never_stops_the_loop(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    assert cycles(monkeypatch, tmp_path, mode=2, fail=True) == [1, "step", 0] * 3


def test_the_hot_path_knows_no_scope_pin() -> None:
    from rtloop.ipc import hotpath, schema

    assert not hasattr(hotpath.PythonCycle, "set_scope_pin") and not hasattr(schema, "ScopeMode")
    if hotpath.c_built():
        assert not hasattr(hotpath._hotpath.Core, "set_scope_pin")
