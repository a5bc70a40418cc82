"""Every number in a device's settings is finite and sane: ``timeout_ms = 1e308`` is one line
naming the device and the key (``devices.motor.timeout_ms: must be at most 3600000``), exit 2,
never an OverflowError from inside a driver."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import ClassVar

import pytest

from rtloop.app.appfile import load_app
from rtloop.errors import AppError
from rtloop.io.device import MAX_SETTING_MAGNITUDE, Setting, build_device

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "dcmotor_serial"


def _serial_app(tmp_path: Path, replace: dict[str, str]) -> Path:
    """The serial DC-motor example in ``tmp_path`` with lines replaced (key → new ``key = value``)."""
    for example in ("dcmotor", "dcmotor_serial"):  # serial_motor.py imports ../dcmotor/dcmotor.py
        shutil.copytree(EXAMPLE.parent / example, tmp_path / example, ignore=shutil.ignore_patterns("__pycache__"))
    app = tmp_path / "dcmotor_serial" / "dcmotor_serial.toml"
    text = app.read_text().replace('name = "dcmotor_serial"', f'name = "numbers_{os.getpid()}"')
    for key, line in replace.items():
        text, count = re.subn(rf"(?m)^{re.escape(key)} = .*$", line, text, count=1)
        assert count == 1, key
    app.write_text(text)
    return app


SERIAL_CASES = {
    "timeout_huge": ({"timeout_ms": "timeout_ms = 1e308"}, "devices.motor.timeout_ms: must be at most 3600000"),
    "timeout_two_hours": ({"timeout_ms": "timeout_ms = 7_200_000"},
                          "devices.motor.timeout_ms: must be at most 3600000, got 7200000.0"),
    "timeout_inf": ({"timeout_ms": "timeout_ms = inf"}, "devices.motor.timeout_ms: must be finite"),
    "baudrate": ({"baudrate": "baudrate = 9_000_000_000_000_000_000"}, "devices.motor.baudrate: must be at most"),
    "stale_count": ({"max_stale_in_a_row": "max_stale_in_a_row = 9_000_000_000_000_000_000"},
                    "devices.motor.max_stale_in_a_row: must be at most 1e+12"),
    "limit_max": ({"max": "max = 1e308"}, "devices.motor.limits.voltage_V: max must be at most 1e+12"),
    "limit_min": ({"min": "min = -1e300"}, "devices.motor.limits.voltage_V: min must be at least -1e+12"),
}


@pytest.mark.parametrize("case", sorted(SERIAL_CASES))
def test_an_absurd_serial_setting_is_refused_when_the_app_loads(tmp_path, case):
    replace, message = SERIAL_CASES[case]
    with pytest.raises(AppError) as refused:
        load_app(_serial_app(tmp_path, replace))
    assert message in str(refused.value)


def test_timeout_1e308_in_simulate_is_one_line_exit_2(tmp_path):
    app = _serial_app(tmp_path, {"timeout_ms": "timeout_ms = 1e308"})
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, "-m", "rtloop", "simulate", str(app), "--duration", "0.05", "--out",
                          str(out)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "devices.motor.timeout_ms: must be at most 3600000" in lines[0], run.stderr
    assert str(app) in lines[0] and not out.exists()


CAN_CASES = {
    "receive_timeout": ({"receive": [{"id": 0x180, "timeout_ms": 1e308}]},
                        "devices.drive.receive[0].timeout_ms: must be at most 3600000"),
    "scale_huge": ({"send": [{"id": 0x200, "signals": [{"name": "a", "start_byte": 0, "scale": 1e308}]}]},
                   "devices.drive.send[0].signals[0].scale: must be at most 1e+12"),
    "scale_tiny": ({"send": [{"id": 0x200, "signals": [{"name": "a", "start_byte": 0, "scale": 1e-320}]}]},
                   "devices.drive.send[0].signals[0].scale: must be at least 1e-12 in size"),
    "offset": ({"receive": [{"id": 0x180, "timeout_ms": 2, "signals": [
        {"name": "a", "start_byte": 0, "offset": -1e200}]}]}, "devices.drive.receive[0].signals[0].offset: must be "
                                                              "at least -1e+12"),
}


@pytest.mark.parametrize("case", sorted(CAN_CASES))
def test_an_absurd_number_in_a_can_frame_is_refused(case):
    settings, message = CAN_CASES[case]
    with pytest.raises(AppError) as refused:
        build_device("can", "drive", {"interface": "vcan0", **settings}, "app.toml")
    assert message in str(refused.value)


@pytest.mark.parametrize("settings, message", [
    ({"speed_hz": 10**18}, "devices.flash.speed_hz: must be at most 1e+12"),
    ({"speed_hz": 300_000_000}, "devices.flash.speed_hz: expected 1..200000000"),
])
def test_an_absurd_spi_speed_is_refused(settings, message):
    with pytest.raises(AppError) as refused:
        build_device("spi", "flash", {"device": "/dev/spidev0.0", "length": 8, **settings}, "app.toml")
    assert message in str(refused.value)


def test_a_gpio_line_offset_beyond_the_kernels_is_refused():
    with pytest.raises(AppError, match=r"devices\.leds\.outputs: a line offset is 0\.\.4294967295, got -1"):
        build_device("gpio", "leds", {"chip": "gpiochip0", "outputs": [-1]}, "app.toml")
    with pytest.raises(AppError, match=r"devices\.leds\.inputs: a line offset is 0\.\.4294967295"):
        build_device("gpio", "leds", {"chip": "gpiochip0", "inputs": [2**40]}, "app.toml")


def test_a_driver_of_ones_own_gets_the_general_bound_and_may_set_its_own():
    from rtloop.io.device import Device

    class Probe(Device):
        settings: ClassVar[dict[str, Setting]] = {
            "rate_hz": Setting(float, 1.0, "how often"),
            "serial": Setting(int, 0, "a serial number", at_most=2**64),
        }

        def read(self, y):
            pass

        def write(self, u):
            pass

    with pytest.raises(AppError, match=r"devices\.probe\.rate_hz: must be at most 1e\+12"):
        build_device(Probe, "probe", {"rate_hz": 1e300}, "app.toml")
    with pytest.raises(AppError, match=r"devices\.probe\.rate_hz: must be at least -1e\+12"):
        build_device(Probe, "probe", {"rate_hz": -MAX_SETTING_MAGNITUDE * 2}, "app.toml")
    assert build_device(Probe, "probe", {"serial": 2**63 - 1}, "app.toml").config["serial"] == 2**63 - 1


def test_an_i2c_bus_given_as_a_path_says_it_is_the_number(tmp_path):
    with pytest.raises(AppError) as refused:
        build_device("i2c", "imu", {"bus": "/dev/i2c-1", "address": 0x68}, "app.toml")
    assert "devices.imu.bus: expected an integer (the I2C bus number N of /dev/i2c-N: bus = 1), got '/dev/i2c-1'" \
        in str(refused.value)


def test_one_i2c_register_written_twice_a_cycle_is_refused_read_back_is_allowed():
    twice = [{"name": "a", "register": 0x10}, {"name": "b", "register": 0x10}]
    with pytest.raises(AppError, match=r"devices\.dac\.writes\[1\]\.register: 0x10 is also written by writes\[0\] "
                                       r"\('a'\); a register is written once a cycle"):
        build_device("i2c", "dac", {"bus": 1, "address": 0x48, "writes": twice}, "app.toml")
    device = build_device("i2c", "dac", {"bus": 1, "address": 0x48, "writes": twice[:1],
                                         "reads": [{"name": "a_back", "register": 0x10}]}, "app.toml")
    assert (device.n_inputs, device.n_outputs) == (1, 1)


def test_a_negative_can_id_is_shown_as_it_was_written():
    with pytest.raises(AppError, match=r"devices\.drive\.send\[0\]\.id: -1 is outside the 11-bit range 0\.\.0x7FF"):
        build_device("can", "drive", {"interface": "vcan0", "send": [{"id": -1}]}, "app.toml")
