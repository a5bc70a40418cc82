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
lists on every call). Where ``io/_devio.c`` was built (``io/compiled.py``), ``write`` and
``read`` are one C call each (``SpiFrame``: the layout packed, counter and CRC sealed, the
ioctl, the answer's CRC and counter checked, its signals unpacked); the Python below is their
reference, with the same bytes, counts and errors (``tests/test_io_compiled.py``).

``write`` does the transfer: it sends the commands and takes the device's answer, which the
next ``read`` checks and unpacks. A ``read`` with no transfer since the previous one (the
first cycle, or a device with nothing to send) transfers the last frame again, with a new
counter, so the device is asked every cycle.
"""

from __future__ import annotations

import os
from typing import Any, ClassVar

from rtloop.errors import DeviceError, DeviceFault
from rtloop.io.bytelayout import FloatView, LayoutError, field_from_table
from rtloop.io.compiled import devio
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
from rtloop.linux import rt

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
    safe_write_is_exchange = True  # the safe values go out in a full-duplex transfer, answered
    settings: ClassVar[dict[str, Setting]] = {
        "device": Setting(str, doc="the spidev node (/dev/spidevB.C)", is_path=True),
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
        self._frame: Any = None  # the cycle in C (io/_devio.c SpiFrame), once configured
        self._u, self._y = FloatView(), FloatView()

    # --- supervisor ---------------------------------------------------------------------------
    def check(self) -> None:
        os.close(self._open())

    def _open(self) -> int:
        if not os.path.exists(self.path):
            nodes = sorted(n for n in os.listdir("/dev") if n.startswith("spidev"))
            found = (f"spidev devices here: {', '.join(nodes)}" if nodes else
                     "this machine has no spidev device: enable its SPI controller (a Raspberry Pi: dtparam=spi=on "
                     "in /boot/firmware/config.txt, then reboot: docs/bench.md); without the hardware, rtloop "
                     "simulate runs the device's twin")
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
                    rt.ioctl(self.fd, request, bytearray(value.to_bytes(size, "little")), f"SPI_IOC_WR {key}")
                except OSError as error:
                    raise DeviceError(self.name, "", key, f"{self.path} refuses {key} = {value}: "
                                      f"{error.strerror}") from None
        except BaseException:
            self.close()
            raise
        self._build_frames()

    def _build_frames(self) -> None:
        """The frames, the transfer pointing at them and their checks, built once (no device needed:
        the tests compare the C cycle with its reference on these buffers anywhere)."""
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
        compiled, send, receive = devio(), self.tx_layout._compiled, self.rx_layout._compiled
        if compiled is not None and send is not None and receive is not None:
            self._frame = compiled.SpiFrame(self.fd, SPI_IOC_MESSAGE_1, self._transfer, self._tx, self._rx, send,
                                            receive, self.counter_check == "echo")

    # --- the cycle: in C where built, else the Python reference ---------------------------------
    def write(self, u: FloatVector) -> None:
        frame = self._frame
        if frame is None:
            self.tx_layout.pack_into(self._tx, 0, self._u.of(u))
            self._exchange()
            return
        try:
            bad = frame.write(u)
        except TypeError:  # not a float64 vector (a list): packed the Python way, transferred in C
            self.tx_layout.pack_into(self._tx, 0, self._u.of(u))
            frame.exchange()
            return
        if bad >= 0:  # a signal that cannot be sent, nothing transferred: the reference names it
            self.tx_layout.pack_into(self._tx, 0, self._u.of(u))  # raises the ValueError for the same field

    def read(self, y: FloatVector) -> None:
        frame = self._frame
        if frame is None:
            if not self._fresh:
                self._exchange()
            self._fresh = False
            if self._answered:
                self.rx_layout.unpack_from(self._rx, 0, self._y.of(y))
            else:
                self._not_valid(self._check.last_error)
            return
        try:
            valid = frame.read(y)
        except TypeError:  # not a float64 vector: checked in C, unpacked the Python way
            valid = frame.read(None)
            if valid:
                self.rx_layout.unpack_from(self._rx, 0, self._y.of(y))
        if not valid:
            self._not_valid(frame.last_error)

    def write_safe(self, u: FloatVector) -> None:
        """The safe values in one transfer, whose answer no cycle reads: the next ``read`` asks the
        device again. (Configure's safe frame goes out before T0; the first cycle reads the device
        as it is at its release, and the twin, which steps on the safe values and again at that
        read, sees as many exchanges as the device.)"""
        self.write(u)
        if self._frame is not None:
            self._frame.read(None)  # takes the answer as read (no transfer: one came since the last read)
        self._fresh = False

    def _not_valid(self, why: str) -> None:
        """The answer failed its CRC or counter check: counted as a stale read, or a fault, as declared."""
        if self.on_error == "stale":
            self.stale_reads += 1
        else:
            raise DeviceFault(f"devices.{self.name}: the answer from {self.path} is not valid: "
                              f"{why} (on_error = \"fault\")")

    def _exchange(self) -> None:
        """One full-duplex transfer of the transmit frame, with the next counter (the reference of
        ``SpiFrame``'s: seal, ioctl, check)."""
        self._seal_frame()
        rt.ioctl(self.fd, SPI_IOC_MESSAGE_1, self._transfer, "SPI_IOC_MESSAGE(1)")
        self._check_answer()

    def _seal_frame(self) -> None:
        """The counter and the CRC into the transmit frame; what the answer must carry."""
        seal(self._tx, self._tx_crc_view, self._counter)
        self._check.sent(self._counter)

    def _check_answer(self) -> bool:
        """Check the answer in the receive frame; the counter moves on. Whether it was valid."""
        self._answered = self._check.accept(self._rx, self._rx_crc_view)
        self._check.after(self._counter)
        self._counter = (self._counter + 1) & 0xFF
        self._fresh = True
        return self._answered

    def may_read_stale(self) -> bool:
        return self.on_error == "stale"

    @property
    def transfers_rejected(self) -> int:
        check = self._frame if self._frame is not None else getattr(self, "_check", None)
        return 0 if check is None else check.bad_crc + check.bad_counter

    def close(self) -> None:
        if self._frame is not None:
            self._check.bad_crc, self._check.bad_counter = self._frame.bad_crc, self._frame.bad_counter  # kept after
            self._frame.release()  # lets go of the buffers, before the descriptor it uses is closed
            self._frame = None
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
