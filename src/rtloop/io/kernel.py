"""Linux ioctl numbers and structs the drivers hand to the kernel, written from its uapi headers.

``tests/test_io_kernel.py`` compiles a few lines of C against the installed headers and checks
every number and size here against the compiler's, so a mistake cannot hide.
"""

from __future__ import annotations

import ctypes
import struct
from typing import Any

# <asm-generic/ioctl.h>: nr 8 bits, type 8 bits, size 14 bits, direction 2 bits (x86-64, arm64).
_IOC_WRITE, _IOC_READ = 1, 2


def _ioc(direction: int, kind: int, number: int, size: int) -> int:
    return (direction << 30) | (size << 16) | (kind << 8) | number


def _iow(kind: int, number: int, size: int) -> int:
    return _ioc(_IOC_WRITE, kind, number, size)


def _iowr(kind: int, number: int, size: int) -> int:
    return _ioc(_IOC_READ | _IOC_WRITE, kind, number, size)


def _ior(kind: int, number: int, size: int) -> int:
    return _ioc(_IOC_READ, kind, number, size)


# <linux/spi/spidev.h>: struct spi_ioc_transfer, 32 bytes, the same layout for 32- and 64-bit userspace.
SPI_IOC_TRANSFER = struct.Struct("=QQIIHBBBBBB")
SPI_IOC_MAGIC = ord("k")
SPI_IOC_MESSAGE_1 = _iow(SPI_IOC_MAGIC, 0, SPI_IOC_TRANSFER.size)
SPI_IOC_WR_MODE = _iow(SPI_IOC_MAGIC, 1, 1)
SPI_IOC_WR_BITS_PER_WORD = _iow(SPI_IOC_MAGIC, 3, 1)
SPI_IOC_WR_MAX_SPEED_HZ = _iow(SPI_IOC_MAGIC, 4, 4)
SPI_IOC_RD_MODE = _ior(SPI_IOC_MAGIC, 1, 1)

# <linux/gpio.h>: struct gpio_v2_line_values { __aligned_u64 bits; __aligned_u64 mask; }
GPIO_V2_LINE_VALUES = struct.Struct("=QQ")
GPIO_V2_LINE_GET_VALUES_IOCTL = _iowr(0xB4, 0x0E, GPIO_V2_LINE_VALUES.size)
GPIO_V2_LINE_SET_VALUES_IOCTL = _iowr(0xB4, 0x0F, GPIO_V2_LINE_VALUES.size)
# struct gpio_v2_line_event: timestamp_ns, id, offset, seqno, line_seqno, padding[6]
GPIO_V2_LINE_EVENT = struct.Struct("=QIIII24x")
GPIO_V2_LINE_EVENT_RISING_EDGE = 1
GPIO_V2_LINE_EVENT_FALLING_EDGE = 2

# <linux/i2c-dev.h>, <linux/i2c.h>
I2C_SLAVE = 0x0703
I2C_FUNCS = 0x0705
I2C_SMBUS = 0x0720
I2C_SMBUS_READ, I2C_SMBUS_WRITE = 1, 0
I2C_SMBUS_BYTE_DATA, I2C_SMBUS_WORD_DATA = 2, 3
I2C_FUNC_SMBUS_READ_BYTE_DATA = 0x00080000
I2C_FUNC_SMBUS_WRITE_BYTE_DATA = 0x00100000
I2C_FUNC_SMBUS_READ_WORD_DATA = 0x00200000
I2C_FUNC_SMBUS_WRITE_WORD_DATA = 0x00400000


class I2cSmbusIoctlData(ctypes.Structure):
    """struct i2c_smbus_ioctl_data { __u8 read_write; __u8 command; __u32 size; union i2c_smbus_data *data; }"""

    _fields_ = [("read_write", ctypes.c_uint8), ("command", ctypes.c_uint8), ("size", ctypes.c_uint32),
                ("data", ctypes.c_void_p)]


I2C_SMBUS_BLOCK_MAX = 32
I2C_SMBUS_DATA_SIZE = I2C_SMBUS_BLOCK_MAX + 2  # union i2c_smbus_data: block[I2C_SMBUS_BLOCK_MAX + 2]

# <sys/ioctl.h>: bytes waiting in a socket's receive queue (the next datagram's size for CAN_RAW)
FIONREAD = 0x541B


def address_of(buffer: bytearray) -> tuple[int, Any]:
    """The address of a bytearray's memory, and the ctypes view that pins it (keep it alive:
    while it exists the bytearray cannot be resized, so the address stays valid)."""
    pin = (ctypes.c_char * len(buffer)).from_buffer(buffer)
    return ctypes.addressof(pin), pin
