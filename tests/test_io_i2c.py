"""I2C driver on the test guest's i2c-stub chips (registers that keep what is written)."""

from __future__ import annotations

import numpy as np
import pytest

from io_guest_devices import KEPT_BYTES_ALLOWED, bytes_kept_by, guest_device
from rtloop.errors import DeviceError
from rtloop.io.device import build_device

pytestmark = pytest.mark.rtkernel  # real kernel interfaces: the PREEMPT_RT test guest


def chip(i2c, **settings):
    table = {"bus": i2c["bus"], "address": i2c["addresses"][0], **settings}
    return build_device("i2c", "sensor", table, "app.toml")


def test_registers_written_and_read_back_with_scale_and_byte_order():
    i2c = guest_device("i2c")
    pytest.importorskip("smbus2", reason="I2C needs smbus2")
    registers = [{"name": "duty", "register": 0x10, "type": "u8", "scale": 0.01},
                 {"name": "speed", "register": 0x20, "type": "i16", "scale": 0.5, "byte_order": "big"},
                 {"name": "temp", "register": 0x30, "type": "u16", "offset": -40.0}]
    device = chip(i2c, writes=registers, reads=registers)
    device.check()
    device.configure()
    try:
        y = np.zeros(3)
        for u in ([0.42, -300.5, 85.0], [2.55, 1000.0, -40.0], [9.99, -1e9, 1e9]):
            device.write(np.array(u))
            device.read(y)
            expected = [min(round(u[0] / 0.01), 255) * 0.01, max(min(round(u[1] / 0.5), 32767), -32768) * 0.5,
                        min(max(round(u[2] + 40.0), 0), 65535) - 40.0]
            assert list(y) == pytest.approx(expected)
        from smbus2 import SMBus

        with SMBus(i2c["bus"]) as bus:  # -32768 big-endian: 0x80 then 0x00; SMBus words come low byte first
            assert bus.read_word_data(i2c["addresses"][0], 0x20) == 0x0080
    finally:
        device.close()


def test_a_missing_bus_or_silent_chip_is_one_line():
    i2c = guest_device("i2c")
    pytest.importorskip("smbus2", reason="I2C needs smbus2")
    with pytest.raises(DeviceError, match=r"devices\.sensor\.bus: no I2C bus /dev/i2c-99"):
        build_device("i2c", "sensor", {"bus": 99, "address": 0x48}, "app.toml").check()
    silent = build_device("i2c", "sensor", {"bus": i2c["bus"], "address": 0x33,
                                            "reads": [{"name": "x", "register": 1}]}, "app.toml")
    with pytest.raises(DeviceError, match=r"devices\.sensor\.address: no answer from 0x33"):
        silent.configure()


def test_no_allocation_in_the_loop():
    i2c = guest_device("i2c")
    pytest.importorskip("smbus2", reason="I2C needs smbus2")
    registers = [{"name": "duty", "register": 0x10, "type": "u8"}, {"name": "speed", "register": 0x20, "type": "i16"}]
    device = chip(i2c, writes=registers, reads=registers)
    device.configure()
    try:
        u, y = np.array([7.0, -300.0]), np.zeros(2)

        def cycle():
            device.write(u)
            device.read(y)

        assert bytes_kept_by(cycle, 10_000) <= KEPT_BYTES_ALLOWED
        assert list(y) == [7.0, -300.0]
    finally:
        device.close()
