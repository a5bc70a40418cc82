"""SPI devices: one full-duplex transfer per cycle of a declared frame, on Linux spidev.

    [devices.fpga]
    kind = "spi"
    device = "/dev/spidev0.0"
    speed_hz = 10_000_000
    mode = 0
    length = 8                       # bytes each way: counter, signals, CRC-16
    send = [{ name = "pwm_pan", start_byte = 1, type = "i16", scale = 0.001 }]
    receive = [{ name = "encoder_pan", start_byte = 1, type = "i32" }]
    counter = "previous"             # or "echo" (MOSI wired to MISO)
    on_error = "fault"               # or "stale": keep the last good values, count

The frame is described in ``io/spiframe.py`` (sequence counter, signals, CRC). Each cycle is
one ``SPI_IOC_MESSAGE(1)`` ioctl with a ``struct spi_ioc_transfer`` built once, pointing at
transmit and receive buffers allocated once (py-spidev's ``xfer2`` allocates and converts
lists on every call).

``write`` does the transfer: it sends the commands and takes the device's answer, which the
next ``read`` checks and unpacks. A ``read`` with no transfer since the previous one (the
first cycle, or a device with nothing to send) transfers the last frame again, with a new
counter, so the device is asked every cycle.
"""

from __future__ import annotations

import fcntl
import os
from typing import Any, ClassVar

from rtloop.errors import DeviceError, DeviceFault
from rtloop.io.bytelayout import FloatView, LayoutError, field_from_table
from rtloop.io.device import Device, FloatVector, Setting
from rtloop.io.kernel import (
    SPI_IOC_MESSAGE_1,
    SPI_IOC_TRANSFER,
    SPI_IOC_WR_BITS_PER_WORD,
    SPI_IOC_WR_MAX_SPEED_HZ,
    SPI_IOC_WR_MODE,
    address_of,
)
from rtloop.io.spiframe import COUNTER_CHECKS, FrameCheck, frame_layout, seal

__all__ = ["SpiDevice"]


def _fields(value: list[Any]) -> str | None:
    if not all(isinstance(item, dict) for item in value):
        return "expected an array of tables ({ name, start_byte, type, scale, offset })"
    return None


def _within(low: int, high: int) -> Any:
    return lambda value: None if low <= value <= high else f"expected {low}..{high}, got {value!r}"


def _one_of(choices: tuple[str, ...]) -> Any:
    return lambda value: None if value in choices else f"expected one of {', '.join(choices)}, got {value!r}"


class SpiDevice(Device):
    """A declared frame exchanged with an SPI device once per cycle (spidev)."""

    kind: ClassVar[str] = "spi"
    settings: ClassVar[dict[str, Setting]] = {
        "device": Setting(str, doc="the spidev node (/dev/spidevB.C)"),
        "speed_hz": Setting(int, 1_000_000, "clock rate in Hz", _within(1, 200_000_000)),
        "mode": Setting(int, 0, "SPI mode 0..3 (clock polarity and phase)", _within(0, 3)),
        "length": Setting(int, doc="bytes of the frame, each way (counter + signals + 2 CRC bytes)",
                          check=_within(3, 4096)),
        "send": Setting(list, [], "signals in the frame sent (start_byte from the frame's first byte)", _fields),
        "receive": Setting(list, [], "signals in the frame received", _fields),
        "counter": Setting(str, "previous", "the counter the device answers with: previous (the frame before) "
                           "or echo (this frame: a loop from MOSI to MISO)", _one_of(COUNTER_CHECKS)),
        "on_error": Setting(str, "fault", "a bad CRC or counter: fault (stop, safe states) or stale (keep the "
                            "last good values, count)", _one_of(("fault", "stale"))),
    }

    def __init__(self, name: str, **settings: Any) -> None:
        super().__init__(name, **settings)
        self.path: str = settings["device"]
        self.speed_hz: int = settings["speed_hz"]
        self.mode: int = settings["mode"]
        self.length: int = settings["length"]
        self.counter_check: str = settings["counter"]
        self.on_error: str = settings["on_error"]
        try:
            self.tx_layout = frame_layout([field_from_table(t, f"send[{i}]") for i, t in enumerate(settings["send"])],
                                          self.length, "send")
            self.rx_layout = frame_layout([field_from_table(t, f"receive[{i}]")
                                           for i, t in enumerate(settings["receive"])], self.length, "receive")
        except LayoutError as error:
            key, _, problem = str(error).partition(": ")
            raise DeviceError(name, "", key, problem) from None
        self.input_names, self.output_names = tuple(self.tx_layout.names), tuple(self.rx_layout.names)
        self.n_inputs, self.n_outputs = len(self.input_names), len(self.output_names)
        self.fd = -1
        self.stale_reads = 0
        self._u, self._y = FloatView(), FloatView()

    # --- supervisor ---------------------------------------------------------------------------
    def check(self) -> None:
        os.close(self._open())

    def _open(self) -> int:
        if not os.path.exists(self.path):
            nodes = sorted(n for n in os.listdir("/dev") if n.startswith("spidev"))
            found = f"spidev devices here: {', '.join(nodes)}" if nodes else "this machine has no spidev device"
            raise DeviceError(self.name, "", "device", f"no SPI device {self.path} ({found})")
        try:
            return os.open(self.path, os.O_RDWR | os.O_CLOEXEC)
        except PermissionError:
            raise DeviceError(self.name, "", "device", f"no permission to open {self.path} (run as root, or add this "
                              "user to the group owning it, often 'spi')") from None
        except OSError as error:
            raise DeviceError(self.name, "", "device", f"cannot open {self.path}: {error.strerror}") from None

    # --- task process ---------------------------------------------------------------------------
    def configure(self) -> None:
        self.fd = self._open()
        try:
            for request, value, size, key in ((SPI_IOC_WR_MODE, self.mode, 1, "mode"),
                                              (SPI_IOC_WR_BITS_PER_WORD, 8, 1, "device"),
                                              (SPI_IOC_WR_MAX_SPEED_HZ, self.speed_hz, 4, "speed_hz")):
                try:
                    fcntl.ioctl(self.fd, request, bytearray(value.to_bytes(size, "little")), True)
                except OSError as error:
                    raise DeviceError(self.name, "", key, f"{self.path} refuses {key} = {value}: "
                                      f"{error.strerror}") from None
        except BaseException:
            self.close()
            raise
        n = self.length
        self._tx, self._rx = bytearray(n), bytearray(n)
        self._tx_crc_view, self._rx_crc_view = memoryview(self._tx)[:n - 2], memoryview(self._rx)[:n - 2]
        tx_address, self._tx_pin = address_of(self._tx)
        rx_address, self._rx_pin = address_of(self._rx)
        self._transfer = bytearray(SPI_IOC_TRANSFER.size)
        SPI_IOC_TRANSFER.pack_into(self._transfer, 0, tx_address, rx_address, n, self.speed_hz, 0, 8, 0, 0, 0, 0, 0)
        self._check = FrameCheck(n, self.counter_check)
        self._counter = 0
        self._answered = self._fresh = False
        seal(self._tx, self._tx_crc_view, 0)

    def _exchange(self) -> None:
        """One full-duplex transfer of the transmit frame, with the next counter."""
        counter = self._counter
        seal(self._tx, self._tx_crc_view, counter)
        self._check.sent(counter)
        fcntl.ioctl(self.fd, SPI_IOC_MESSAGE_1, self._transfer, True)
        self._answered = self._check.accept(self._rx, self._rx_crc_view)
        self._check.after(counter)
        self._counter = (counter + 1) & 0xFF
        self._fresh = True

    def write(self, u: FloatVector) -> None:
        self.tx_layout.pack_into(self._tx, 0, self._u.of(u))
        self._exchange()

    def read(self, y: FloatVector) -> None:
        if not self._fresh:
            self._exchange()
        self._fresh = False
        if self._answered:
            self.rx_layout.unpack_from(self._rx, 0, self._y.of(y))
        elif self.on_error == "stale":
            self.stale_reads += 1
        else:
            raise DeviceFault(f"devices.{self.name}: the answer from {self.path} is not valid: "
                              f"{self._check.last_error} (on_error = \"fault\")")

    def may_read_stale(self) -> bool:
        return self.on_error == "stale"

    @property
    def transfers_rejected(self) -> int:
        check = getattr(self, "_check", None)
        return 0 if check is None else check.bad_crc + check.bad_counter

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
