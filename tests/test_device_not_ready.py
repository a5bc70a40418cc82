"""A device declared right that refuses at start — its port not there yet, busy, silent at configure —
is exit 3, not 2: the app file is fine, and the service's unit (which never restarts exit 2) retries
it. A driver library that is missing stays bad input (exit 2)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name
from device_test_drivers import Echo
from rtloop import App
from rtloop.cli.main import exit_code_for, main
from rtloop.errors import DeviceError, DeviceNotReady

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "dcmotor_serial"


def test_a_serial_port_not_there_yet_is_exit_3_and_one_line(tmp_path: Path) -> None:
    for example in ("dcmotor", "dcmotor_serial"):  # serial_motor.py imports ../dcmotor/dcmotor.py
        shutil.copytree(EXAMPLE.parent / example, tmp_path / example, ignore=shutil.ignore_patterns("__pycache__"))
    app = tmp_path / "dcmotor_serial" / "dcmotor_serial.toml"
    text = app.read_text().replace('name = "dcmotor_serial"', f'name = "{unique_name("notready")}"')
    text, count = re.subn(r'(?m)^port = ".*?"', f'port = "{tmp_path / "ttyUSB9"}"', text)
    assert count == 1
    app.write_text(text)
    done = subprocess.run([sys.executable, "-m", "rtloop", "run", str(app), "--duration", "1", "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 3, done.stderr
    assert done.stderr.count("\n") == 1 and f"devices.motor.port: {tmp_path / 'ttyUSB9'} does not exist" in done.stderr
    assert not (tmp_path / "out").exists()


def test_a_device_silent_at_configure_is_not_ready(tmp_path: Path) -> None:
    app = App(unique_name("notready_cfg"))
    ctl = app.add_task("ctl", Echo(), period_ns=2_000_000)
    dev = app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(tmp_path / "dev.log"),
                         fail_in="configure", limits={"c0": {"min": -1.0, "max": 1.0, "safe": 0.0}})
    app.connect(ctl.y[0], dev.u[0])
    with pytest.raises(DeviceNotReady, match=r"devices\.dev\.fail_in: the device did not answer"):
        rtloop.run(app, 1.0, tmp_path / "out")


def test_exit_codes_of_device_errors() -> None:
    assert exit_code_for(DeviceNotReady("motor", "app.toml", "port", "not there")) == 3
    assert exit_code_for(DeviceError("motor", "app.toml", "timeout_ms", "must be at most 3600000")) == 2
    missing_library = DeviceNotReady.of(DeviceError("imu", "app.toml", "kind", "I2C needs smbus2"))
    assert type(missing_library) is DeviceError and exit_code_for(missing_library) == 2


def test_the_unit_restarts_exit_3_and_not_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["service", str(EXAMPLE / "dcmotor_serial.toml")]) == 0
    unit = capsys.readouterr().out
    assert "RestartPreventExitStatus=2\n" in unit and "Restart=on-failure\n" in unit
    assert "a device not ready at" in unit and "(exit 3:" in unit
