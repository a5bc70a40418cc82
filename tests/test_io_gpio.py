"""GPIO driver on gpio-sim lines in the PREEMPT_RT test guest (skips elsewhere, saying why)."""

from __future__ import annotations

import select
import time

import numpy as np
import pytest

from io_guest_devices import KEPT_BYTES_ALLOWED, SimLine, bytes_kept_by, guest_device
from rtloop.errors import DeviceError
from rtloop.io.device import build_device
from rtloop.io.gpio import EmergencyStop

pytestmark = pytest.mark.rtkernel  # real kernel interfaces: the PREEMPT_RT test guest


@pytest.fixture
def gpio():
    entry = guest_device("gpio")
    pytest.importorskip("gpiod", reason="GPIO needs gpiod >= 2 (pip install 'gpiod>=2')")
    return entry


def device(gpio, **settings):
    return build_device("gpio", "panel", {"chip": gpio["device"], **settings}, "app.toml")


def test_outputs_and_inputs_by_name_and_offset(gpio):
    panel = device(gpio, outputs=["led", str(gpio["lines"]["enable"]["offset"])], inputs=["button", "fault"])
    led, enable, button, fault = (SimLine(gpio, n) for n in ("led", "enable", "button", "fault"))
    panel.check()
    panel.configure()
    try:
        y = np.zeros(2)
        for u in ([1.0, 0.0], [0.0, 1.0], [0.7, 0.2]):
            panel.write(np.array(u))
            assert (led.value, enable.value) == (int(u[0] >= 0.5), int(u[1] >= 0.5))
        for pressed in (True, False, True):
            button.pull(pressed)
            fault.pull(not pressed)
            panel.read(y)
            assert list(y) == [float(pressed), float(not pressed)]
    finally:
        panel.close()
    button.pull(False)


def test_a_busy_line_is_one_line_naming_it(gpio):
    import gpiod

    with gpiod.Chip(gpio["device"]) as chip:
        holder = chip.request_lines({"led": None}, consumer="someone-else")
        try:
            with pytest.raises(DeviceError, match=r"devices\.panel\.outputs: line 'led' .* is busy: in use by "
                                                  r"'someone-else'") as error:
                device(gpio, outputs=["led"]).check()
            assert "\n" not in str(error.value)
        finally:
            holder.release()


def test_a_missing_chip_or_line_is_one_line(gpio):
    with pytest.raises(DeviceError, match=r"devices\.panel\.chip: no GPIO chip /dev/gpiochip99 \(chips here: "):
        build_device("gpio", "panel", {"chip": "gpiochip99", "outputs": ["led"]}, "app.toml").check()
    with pytest.raises(DeviceError, match=r"devices\.panel\.outputs: no line 'nosuchline'"):
        device(gpio, outputs=["nosuchline"]).check()


def test_estop_edge_stops_with_its_kernel_timestamp(gpio):
    estop = SimLine(gpio, "estop")
    estop.pull(True)  # released: a normally-closed contact holds the line high
    panel = device(gpio, outputs=["led"], estop="estop", estop_edge="falling")
    panel.configure()
    try:
        y = np.zeros(0)
        panel.read(y)  # no edge: nothing happens
        before = time.monotonic_ns()
        estop.pull(False)  # pressed
        # the simulator raises its interrupt from a kernel thread (irq_work on PREEMPT_RT): the
        # edge is queued a moment later, as a real one would be seen at the next release
        assert select.select([panel._estop.fd], [], [], 5.0)[0], "no edge event from gpio-sim"
        with pytest.raises(EmergencyStop) as stop:
            panel.read(y)
        assert before <= stop.value.timestamp_ns <= time.monotonic_ns()
        assert stop.value.to_json() == {"device": "panel", "line": "estop", "edge": "falling",
                                        "edge_ns": stop.value.timestamp_ns}
    finally:
        panel.close()
        estop.pull(True)


def test_an_engaged_estop_refuses_to_start(gpio):
    estop = SimLine(gpio, "estop")
    estop.pull(False)
    try:
        with pytest.raises(DeviceError, match="E-stop line 'estop' is engaged"):
            device(gpio, estop="estop", estop_edge="falling").configure()
    finally:
        estop.pull(True)


def test_scope_line_is_the_scope_pins_bit(gpio):
    import fcntl

    from rtloop.io.kernel import GPIO_V2_LINE_SET_VALUES_IOCTL, GPIO_V2_LINE_VALUES

    panel = device(gpio, outputs=["led"], scope_pin="scope")
    scope, led = SimLine(gpio, "scope"), SimLine(gpio, "led")
    panel.configure()
    try:
        fd, request, bit, mode = panel.scope_output()
        assert (request, mode) == (GPIO_V2_LINE_SET_VALUES_IOCTL, 1)
        values = bytearray(GPIO_V2_LINE_VALUES.size)
        for level in (1, 0, 1):
            GPIO_V2_LINE_VALUES.pack_into(values, 0, level << bit, 1 << bit)
            fcntl.ioctl(fd, request, values, True)
            assert scope.value == level and led.value == 0
    finally:
        panel.close()


def test_no_allocation_in_the_loop(gpio):
    panel = device(gpio, outputs=["led", "enable"], inputs=["button", "fault"], estop="estop")
    SimLine(gpio, "estop").pull(True)
    panel.configure()
    try:
        u, y = np.array([1.0, 0.0]), np.zeros(2)

        def cycle():
            u[0] = 1.0 - u[0]
            panel.write(u)
            panel.read(y)

        assert bytes_kept_by(cycle, 10_000) <= KEPT_BYTES_ALLOWED
    finally:
        panel.close()
