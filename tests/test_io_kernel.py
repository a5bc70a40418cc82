"""The ioctl numbers and struct sizes in ``rtloop.io.kernel`` equal the C compiler's, from the uapi headers."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from rtloop.io import canframes, kernel

PROBE = r"""
#include <stdio.h>
#include <stddef.h>
#include <sys/ioctl.h>
#include <linux/can.h>
#include <linux/gpio.h>
#include <linux/i2c.h>
#include <linux/i2c-dev.h>
#include <linux/spi/spidev.h>
int main(void) {
    printf("%zu %lu %lu %lu %lu %lu\n", sizeof(struct spi_ioc_transfer), (unsigned long)SPI_IOC_MESSAGE(1),
           (unsigned long)SPI_IOC_WR_MODE, (unsigned long)SPI_IOC_WR_BITS_PER_WORD,
           (unsigned long)SPI_IOC_WR_MAX_SPEED_HZ, (unsigned long)SPI_IOC_RD_MODE);
    printf("%zu %lu %lu %zu\n", sizeof(struct gpio_v2_line_values), (unsigned long)GPIO_V2_LINE_GET_VALUES_IOCTL,
           (unsigned long)GPIO_V2_LINE_SET_VALUES_IOCTL, sizeof(struct gpio_v2_line_event));
    printf("%zu %zu %zu %lu %lu %lu\n", sizeof(struct i2c_smbus_ioctl_data),
           offsetof(struct i2c_smbus_ioctl_data, data), sizeof(union i2c_smbus_data),
           (unsigned long)I2C_SLAVE, (unsigned long)I2C_SMBUS, (unsigned long)I2C_FUNCS);
    printf("%zu %zu %zu %lu\n", sizeof(struct can_frame), sizeof(struct canfd_frame),
           offsetof(struct canfd_frame, data), (unsigned long)FIONREAD);
    return 0;
}
"""


@pytest.fixture(scope="module")
def compiled(tmp_path_factory):
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler here to read the kernel's uapi headers with")
    folder = tmp_path_factory.mktemp("probe")
    (folder / "probe.c").write_text(PROBE)
    built = subprocess.run([compiler, "-o", str(folder / "probe"), str(folder / "probe.c")],
                           capture_output=True, text=True)
    if built.returncode != 0:
        pytest.skip(f"the kernel's uapi headers are not installed here: {built.stderr.strip().splitlines()[0]}")
    out = subprocess.run([str(folder / "probe")], capture_output=True, text=True, check=True).stdout
    return [list(map(int, line.split())) for line in out.splitlines()]


def test_spi_ioc_transfer_is_32_bytes_and_the_ioctls_match(compiled):
    assert compiled[0] == [kernel.SPI_IOC_TRANSFER.size, kernel.SPI_IOC_MESSAGE_1, kernel.SPI_IOC_WR_MODE,
                           kernel.SPI_IOC_WR_BITS_PER_WORD, kernel.SPI_IOC_WR_MAX_SPEED_HZ, kernel.SPI_IOC_RD_MODE]
    assert kernel.SPI_IOC_TRANSFER.size == 32


def test_gpio_v2_values_and_event(compiled):
    assert compiled[1] == [kernel.GPIO_V2_LINE_VALUES.size, kernel.GPIO_V2_LINE_GET_VALUES_IOCTL,
                           kernel.GPIO_V2_LINE_SET_VALUES_IOCTL, kernel.GPIO_V2_LINE_EVENT.size]


def test_i2c_smbus(compiled):
    import ctypes
    assert compiled[2] == [ctypes.sizeof(kernel.I2cSmbusIoctlData), kernel.I2cSmbusIoctlData.data.offset,
                           kernel.I2C_SMBUS_DATA_SIZE, kernel.I2C_SLAVE, kernel.I2C_SMBUS, kernel.I2C_FUNCS]


def test_can_frames(compiled):
    assert compiled[3] == [canframes.CLASSIC_MTU, canframes.FD_MTU, canframes.DATA_AT, kernel.FIONREAD]


def test_a_failed_ioctl_names_the_request_and_its_errno() -> None:
    """Before: fcntl.ioctl's bare OSError ("[Errno 25] Inappropriate ioctl for device") named no call."""
    import errno
    import os

    from rtloop.errors import LibcError
    from rtloop.io.kernel import GPIO_V2_LINE_SET_VALUES_IOCTL
    from rtloop.linux import rt

    fd = os.open("/dev/null", os.O_RDWR)
    try:
        with pytest.raises(LibcError) as caught:
            rt.ioctl(fd, GPIO_V2_LINE_SET_VALUES_IOCTL, bytearray(16), "GPIO_V2_LINE_SET_VALUES_IOCTL")
    finally:
        os.close(fd)
    assert caught.value.errno == errno.ENOTTY and isinstance(caught.value, OSError)  # callers catching OSError still do
    assert str(caught.value).startswith(f"ioctl(GPIO_V2_LINE_SET_VALUES_IOCTL) on fd {fd} failed: ")
