"""SPI driver on the test guest's loopback controller (MOSI copied to MISO) through spidev."""

from __future__ import annotations

import numpy as np
import pytest

from io_guest_devices import KEPT_BYTES_ALLOWED, bytes_kept_by, guest_device
from rtloop.errors import DeviceError, DeviceFault
from rtloop.io.device import build_device

pytestmark = pytest.mark.rtkernel  # real kernel interfaces: the PREEMPT_RT test guest

SIGNALS = [{"name": "pwm_pan", "start_byte": 1, "type": "i16", "scale": 0.001},
           {"name": "pwm_tilt", "start_byte": 3, "type": "i16", "scale": 0.001},
           {"name": "enable", "start_byte": 5, "type": "u8"}]


def fpga(path, **settings):
    table = {"device": path, "length": 8, "send": SIGNALS, "receive": SIGNALS, "counter": "echo", **settings}
    return build_device("spi", "fpga", table, "app.toml")


def test_a_frame_goes_out_and_comes_back_counter_and_crc_checked():
    spi = guest_device("spi")
    device = fpga(spi["devices"][0])
    device.check()
    device.configure()
    try:
        y = np.zeros(3)
        for cycle in range(300):  # the counter wraps at 256
            u = np.array([0.5 - cycle * 0.001, -0.25, 1.0])
            device.write(u)
            device.read(y)
            assert list(y) == [round(u[0] / 0.001) * 0.001, -0.25, 1.0]  # value = raw * scale
            assert device._tx[0] == cycle & 0xFF and device._rx == device._tx
        assert device.transfers_rejected == 0
    finally:
        device.close()


def test_an_answer_with_the_wrong_counter_is_a_fault_or_stale():
    spi = guest_device("spi")
    # a device that answers the frame before: the loop gives back this frame's counter instead
    device = fpga(spi["devices"][0], counter="previous")
    device.configure()
    try:
        y = np.zeros(3)
        device.write(np.array([0.1, 0.2, 1.0]))
        device.read(y)  # the first answer has nothing to compare with
        device.write(np.array([0.1, 0.2, 1.0]))
        with pytest.raises(DeviceFault, match="counter 1 where 0 was expected"):
            device.read(y)
    finally:
        device.close()
    stale = fpga(spi["devices"][1], counter="previous", on_error="stale")
    stale.configure()
    try:
        y = np.zeros(3)
        for _ in range(3):
            stale.write(np.array([0.1, 0.2, 1.0]))
            stale.read(y)
        assert stale.stale_reads == 2 and stale.transfers_rejected == 2
    finally:
        stale.close()


def test_read_without_write_still_asks_the_device_each_cycle():
    spi = guest_device("spi")
    device = fpga(spi["devices"][0], send=[])
    device.configure()
    try:
        y = np.zeros(3)
        for cycle in range(3):
            device.read(y)
            assert device._rx[0] == cycle
    finally:
        device.close()


@pytest.mark.parametrize("hot_path", ["c", "python"])
def test_the_first_read_after_the_safe_values_transfers_again(hot_path, monkeypatch):
    """Configure's safe frame goes out before T0; the first cycle asks the device anew (its answer
    to the safe frame would be as old as the start-up), through the C cycle and its reference."""
    spi = guest_device("spi")
    monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1" if hot_path == "python" else "0")
    device = fpga(spi["devices"][0])
    device.configure()
    try:
        assert (device._frame is not None) == (hot_path == "c")
        y = np.zeros(3)
        device.write_safe(np.zeros(3))
        assert device._tx[0] == 0
        device.read(y)  # a second transfer: the counter moved on
        assert device._tx[0] == 1 and device._rx[0] == 1 and list(y) == [0.0, 0.0, 0.0]
        device.write(np.array([0.5, 0.25, 1.0]))
        device.read(y)  # answered since the last read: no transfer
        assert device._tx[0] == 2 and list(y) == [0.5, 0.25, 1.0]
    finally:
        device.close()


def test_a_missing_device_or_no_permission_is_one_line(tmp_path):
    spi = guest_device("spi")
    with pytest.raises(DeviceError, match=r"devices\.fpga\.device: no SPI device /dev/spidev9\.9 \(spidev devices "
                                          r"here: spidev"):
        fpga("/dev/spidev9.9").check()
    import os
    import pwd
    import subprocess
    import sys

    try:
        nobody = pwd.getpwnam("nobody")
    except KeyError:
        pytest.skip("no user 'nobody' to try without permission")
    code = ("from rtloop.io.device import build_device\n"
            f"build_device('spi', 'fpga', {{'device': {spi['devices'][0]!r}, 'length': 8}}, 'app.toml').check()")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, user=nobody.pw_uid,
                         group=nobody.pw_gid, cwd=tmp_path, env={**os.environ, "HOME": str(tmp_path)})
    assert "no permission to open" in run.stderr


def test_no_allocation_in_the_loop():
    spi = guest_device("spi")
    device = fpga(spi["devices"][0])
    device.configure()
    try:
        u, y = np.array([0.25, -0.5, 1.0]), np.zeros(3)

        def cycle():
            device.write(u)
            device.read(y)

        assert bytes_kept_by(cycle, 10_000) <= KEPT_BYTES_ALLOWED
        assert list(y) == [0.25, -0.5, 1.0] and device.transfers_rejected == 0
    finally:
        device.close()
