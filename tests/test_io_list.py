"""`rtloop io list` and the doctor's devices check, on this machine and on a prepared /dev + /sys tree."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from conftest import require_nobody_can_import_rtloop
from rtloop.cli.doctor import check_devices
from rtloop.io.inventory import format_table, list_interfaces


def _tree(root: Path) -> Path:
    """A machine with one of each: a GPIO chip, a vcan that is down, spidev, a USB serial adapter, I2C."""
    def write(relative: str, text: str = "") -> None:
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)

    for node in ("gpiochip0", "spidev0.0", "ttyUSB0", "i2c-1"):
        write(f"dev/{node}")
    write("sys/bus/gpio/devices/gpiochip0/label", "gpio-sim.0-node0\n")
    write("sys/class/net/vcan0/type", "280\n")
    write("sys/class/net/vcan0/operstate", "down\n")
    write("sys/class/net/vcan0/flags", "0x80\n")
    write("sys/class/net/vcan0/mtu", "72\n")
    write("sys/class/net/eth0/type", "1\n")
    write("sys/class/tty/ttyUSB0/device/latency_timer", "16\n")
    (root / "sys/bus/usb-serial/drivers/ftdi_sio").mkdir(parents=True)
    (root / "sys/class/tty/ttyUSB0/device/driver").symlink_to(root / "sys/bus/usb-serial/drivers/ftdi_sio")
    write("sys/class/tty/ttyS3/type", "0\n")  # a legacy port with no UART: not listed
    (root / "sys/class/tty/ttyS3/device").mkdir()
    (root / "sys/class/tty/ttyS3/device/driver").symlink_to(root / "sys/bus/usb-serial/drivers/ftdi_sio")
    write("dev/ttyS3")
    write("sys/class/i2c-dev/i2c-1/name", "SMBus stub driver\n")
    return root


def test_every_kind_is_listed_with_what_it_is(tmp_path: Path) -> None:
    found = {item.kind: item for item in list_interfaces(_tree(tmp_path))}
    assert set(found) == {"gpio", "can", "spi", "serial", "i2c"}
    assert found["gpio"].path == "/dev/gpiochip0" and "gpio-sim.0-node0" in found["gpio"].detail
    can = found["can"]
    assert (can.path, can.usable) == ("vcan0", False) and "down" in can.detail and "CAN FD" in can.detail
    assert can.fix == "sudo ip link set vcan0 up"
    assert found["serial"].detail == "driver ftdi_sio, latency_timer 16 ms (set 1 for a 1 kHz loop)"
    assert found["i2c"].detail == "SMBus stub driver"
    table = format_table(list_interfaces(tmp_path))
    assert "fix: sudo ip link set vcan0 up" in table and "/dev/ttyS3" not in table


def test_the_doctor_says_which_cannot_be_used_and_the_fix(tmp_path: Path) -> None:
    check = check_devices(_tree(tmp_path))
    assert check.status == "warn" and "vcan0" in check.detail and "sudo ip link set vcan0 up" in check.fix
    empty = check_devices(tmp_path / "nothing")
    assert empty.status == "ok" and "no GPIO chip" in empty.detail
    one = tmp_path / "one"
    (one / "dev").mkdir(parents=True)
    (one / "dev" / "i2c-1").write_text("")
    assert check_devices(one).detail.startswith("1 interface (i2c), all usable")  # not "1 interfaces"


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None,
                    reason="needs root and setpriv to look as another user")
def test_a_device_this_user_may_not_open_says_the_fix() -> None:
    require_nobody_can_import_rtloop()
    root = Path(tempfile.mkdtemp(prefix="rtloop-io-"))
    try:
        _tree(root)
        for path in [root, *root.rglob("*")]:
            if not path.is_symlink():
                path.chmod(0o755 if path.is_dir() else 0o644)
        (root / "dev" / "spidev0.0").chmod(0o600)
        code = f"import json; from rtloop.io.inventory import list_interfaces; " \
               f"print(json.dumps([i.to_json() for i in list_interfaces(__import__('pathlib').Path('{root}'))]))"
        result = subprocess.run(["setpriv", "--reuid", "65534", "--regid", "65534", "--clear-groups",
                                 sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, result.stderr
        spi = next(item for item in json.loads(result.stdout) if item["kind"] == "spi")
        assert spi["usable"] is False and "udev rule" in spi["fix"]
    finally:
        shutil.rmtree(root)


def test_rtloop_io_list_runs_here() -> None:
    result = subprocess.run([sys.executable, "-m", "rtloop", "io", "list"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(("kind", "no GPIO chip"))
    as_json = subprocess.run([sys.executable, "-m", "rtloop", "io", "list", "--json"], capture_output=True,
                             text=True, timeout=60)
    assert isinstance(json.loads(as_json.stdout), list)
