"""The SPI frame exchanged once per cycle: a sequence counter, the signals, a CRC.

    byte 0            sequence counter (0..255, +1 every cycle)
    bytes 1..n-3      the declared signals (``start_byte`` counts from the frame's first byte)
    bytes n-2, n-1    CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of bytes 0..n-3, big-endian

The same shape goes both ways in one full-duplex transfer. What comes back is checked: a
CRC that does not match, or a counter that is not the expected one, means the frame was
not the device's answer (noise, a device not listening, a stuck bus): the values are not
used. The counter the device answers with is declared: ``previous`` (the counter of the
frame before: a device prepares its answer before the transfer that carries it) or
``echo`` (the counter of the same transfer: a wire loop from MOSI to MISO, the test setup).

CRC-16/CCITT-FALSE because it is what FPGA and microcontroller CRC blocks offer and what
``binascii.crc_hqx`` computes in C (its check value: 0x29B1 for ``b"123456789"``).
"""

from __future__ import annotations

import binascii
from collections.abc import Sequence

from rtloop.io.bytelayout import ByteLayout, Field, LayoutError

CRC_INIT = 0xFFFF
COUNTER_CHECKS = ("previous", "echo")
SEQUENCE_FIELD = "sequence counter"
CRC_FIELD = "CRC"


def crc16_ccitt(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE of ``data``."""
    return binascii.crc_hqx(data, CRC_INIT)


def frame_layout(fields: Sequence[Field], length_bytes: int, where: str) -> ByteLayout:
    """The signals of one direction, checked against the counter and CRC bytes they must leave free."""
    if length_bytes < 3:
        raise LayoutError(f"{where}: a frame of {length_bytes} bytes has no room for the counter and the CRC "
                          "(3 bytes at least)")
    needed = max((field.start_byte + field.size_bytes for field in fields), default=1) + 2
    grow = f"; the frame's {length_bytes} bytes hold the counter, the signals and the CRC from length {needed}"
    for index, field in enumerate(fields):  # named by its index in the app file (the counter and CRC are not)
        at, end = f"{where}[{index}] ({field.name!r})", field.start_byte + field.size_bytes
        if field.start_byte == 0:
            raise LayoutError(f"{at}: byte 0 is also used by the {SEQUENCE_FIELD} (byte 0); signals start at byte 1")
        if end > length_bytes:
            raise LayoutError(f"{at}: a {field.type} at byte {field.start_byte} ends at byte {end}, past the frame's "
                              f"{length_bytes} bytes{grow}")
        if end > length_bytes - 2:
            raise LayoutError(f"{at}: byte {max(field.start_byte, length_bytes - 2)} is also used by the {CRC_FIELD} "
                              f"(bytes {length_bytes - 2} and {length_bytes - 1}){grow}")
    return ByteLayout(fields, length_bytes, where)  # overlaps between signals


class FrameCheck:
    """What a received frame must satisfy; counts what did not."""

    __slots__ = ("bad_counter", "bad_crc", "counter_check", "expected", "last_error", "length_bytes")

    def __init__(self, length_bytes: int, counter_check: str) -> None:
        self.length_bytes = length_bytes
        self.counter_check = counter_check
        self.expected = -1  # no expectation before the first transfer when the device answers the previous one
        self.bad_crc = 0
        self.bad_counter = 0
        self.last_error = ""

    def sent(self, counter: int) -> None:
        """Note the counter of the frame just sent (call before ``accept`` for the same transfer)."""
        if self.counter_check == "echo":
            self.expected = counter
        # "previous": ``expected`` was set by the transfer before (-1 for the very first one)

    def after(self, counter: int) -> None:
        """The transfer is over: what the next answer must carry."""
        if self.counter_check == "previous":
            self.expected = counter

    def accept(self, frame: bytearray, crc_view: memoryview) -> bool:
        """True when ``frame`` carries a good CRC and the expected counter (``crc_view``: its first n-2 bytes)."""
        n = self.length_bytes
        if binascii.crc_hqx(crc_view, CRC_INIT) != (frame[n - 2] << 8 | frame[n - 1]):
            self.bad_crc += 1
            self.last_error = "bad CRC"
            return False
        if self.expected >= 0 and frame[0] != self.expected:
            self.bad_counter += 1
            self.last_error = f"counter {frame[0]} where {self.expected} was expected"
            return False
        return True


def seal(frame: bytearray, crc_view: memoryview, counter: int) -> None:
    """Put the counter in byte 0 and the CRC of everything before the last two bytes at the end."""
    frame[0] = counter
    crc = binascii.crc_hqx(crc_view, CRC_INIT)
    n = len(frame)
    frame[n - 2] = crc >> 8
    frame[n - 1] = crc & 0xFF
