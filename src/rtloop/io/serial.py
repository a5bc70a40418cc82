"""Serial devices: one framed request/response per cycle, with a timeout.

The protocol is small enough to implement on any microcontroller. Both directions use
the same frame; all numbers little-endian::

    sync     length       sequence   flags     payload (length bytes)  CRC (2 bytes)
    0xA5 request  = 8 × values  0..255     bit 0:    values as float64       CRC-16/XMODEM
    0x5A response               (echoed)   enabled                           of length..payload

A request carries the commands (``u``), the response the readings (``y``), so one exchange
is one cycle: the device applies the commands and answers what it measures. A request's
``enabled`` flag is set from ``activate`` (T0) until the safe values at the end; the
response's says whether the device's output is on. While enabled, every request is the
device's **heartbeat**: a device that hears none for its timeout must go to its safe state
by itself (the host cannot, once its process is killed), and say so in its responses: the
host then stops the app with a fault rather than command a device that is not listening.

The exchange happens in ``write`` (the time a LET device's commands are due: the release);
``read`` hands over the readings of the last exchange. An answer that does not come whole and
good within ``timeout_ms`` is a fault (``on_missing = "fault"``), or (``"stale"``) the cycle
keeps the last readings and counts a stale read: the next exchange drops what is left in the
input and passes over late answers to earlier requests (their sequence numbers tell), and
``max_stale_in_a_row`` exchanges in a row without an answer are a fault all the same (a device
that stopped answering is not a device to keep commanding). pyserial opens and sets up the port
(raw mode, baud rate, exclusive lock); each cycle then costs one ``os.write`` and a
``poll`` + ``os.readv`` or two on its file descriptor into buffers allocated once.
"""

from __future__ import annotations

import binascii
import grp
import os
import select
import stat
import termios
import time
from typing import Any, ClassVar

import numpy as np

from rtloop.errors import DeviceError, DeviceFault
from rtloop.io.device import HOUR_MS, Device, FloatVector, Setting, positive
from rtloop.sudo import trusted_uids, trusted_users_phrase
from rtloop.text import counted

REQUEST_SYNC = 0xA5
RESPONSE_SYNC = 0x5A
HEADER_BYTES = 4
ENABLED = 0x01
"""Flags bit: outputs enabled (request), output on (response)."""
CRC_BYTES = 2
ON_MISSING = ("fault", "stale")
SAFE_EXCHANGE_MIN_NS = 100_000_000
"""The safe exchange (before T0 and on the way out, not in the loop) waits at least 100 ms for
its answer: a line that is merely slow must not turn a safe state that went out into a failure."""
STALE_SOURCES = ("no answer within timeout_ms", "bad frame (sync, length or CRC)")
MAX_VALUES = 31
"""At most 31 float64 values each way (248 payload bytes: the length fits one byte)."""


def frame_bytes(n_values: int) -> int:
    return HEADER_BYTES + 8 * n_values + CRC_BYTES


def crc16(data: Any) -> int:
    """CRC-16/XMODEM (polynomial 0x1021, initial 0): ``binascii.crc_hqx``, computed in C."""
    return binascii.crc_hqx(data, 0)


class Frame:
    """One frame's bytes, allocated once, with a float64 view of its payload."""

    def __init__(self, sync: int, n_values: int) -> None:
        self.sync, self.n_values = sync, n_values
        self.buffer = bytearray(frame_bytes(n_values))
        self.view = memoryview(self.buffer)
        self.values = np.frombuffer(self.buffer, dtype="<f8", count=n_values, offset=HEADER_BYTES)
        self.buffer[0], self.buffer[1] = sync, 8 * n_values
        self.crc_at = HEADER_BYTES + 8 * n_values
        self.checked = self.view[1 : self.crc_at]  # what the CRC covers

    @property
    def sequence(self) -> int:
        return self.buffer[2]

    @property
    def enabled(self) -> bool:
        return bool(self.buffer[3] & ENABLED)

    def seal(self, sequence: int, flags: int) -> None:
        """Stamp the sequence number, the flags and the CRC (after ``values`` were filled)."""
        self.buffer[2], self.buffer[3] = sequence, flags
        crc = crc16(self.checked)
        self.buffer[self.crc_at], self.buffer[self.crc_at + 1] = crc & 0xFF, crc >> 8

    def problem(self, sequence: int | None = None) -> str | None:
        """What is wrong with the bytes received (None: a good frame)."""
        buffer = self.buffer
        if buffer[0] != self.sync:
            return f"sync byte 0x{buffer[0]:02x}, expected 0x{self.sync:02x}"
        if buffer[1] != 8 * self.n_values:
            return f"length {buffer[1]}, expected {8 * self.n_values} ({self.n_values} values)"
        if crc16(self.checked) != buffer[self.crc_at] | buffer[self.crc_at + 1] << 8:
            return "CRC mismatch"
        if sequence is not None and buffer[2] != sequence:
            return f"sequence {buffer[2]}, expected {sequence} (an answer to another request)"
        return None


def read_frame(fd: int, frame: Frame, poller: Any, timeout_ns: int) -> bool:
    """Fill ``frame`` from ``fd`` within ``timeout_ns``; False on timeout (nothing allocated that stays),
    EOFError when the other end closed the line."""
    deadline_ns = time.monotonic_ns() + timeout_ns
    view, size, got = frame.view, len(frame.buffer), 0
    while got < size:
        left_ns = deadline_ns - time.monotonic_ns()
        if left_ns <= 0 or not poller.poll(max(1, -(-left_ns // 1_000_000))):
            return False
        received = os.readv(fd, (view[got:],))
        if received == 0:
            raise EOFError("end of file")
        got += received
    return True


def _at_least_one(value: int) -> str | None:
    return None if value >= 1 else f"must be at least 1, got {value!r}"


def _on_missing(value: str) -> str | None:
    return None if value in ON_MISSING else f"expected one of {', '.join(ON_MISSING)}, got {value!r}"


def _names(value: list[Any]) -> str | None:
    if not all(isinstance(name, str) and name.isidentifier() for name in value):
        return "expected names (letters, digits, underscores)"
    return None if len(set(value)) == len(value) else "a name is given twice"


def foreign_owner(path: str, opened: os.stat_result | None = None) -> str | None:
    """Why ``path`` may lead to another user's line (None: it does not). A symbolic link on the
    way owned by another user, or a device node of theirs (a pty they hold the other end of),
    would let them read every command and answer as the device. A tty of root:dialout is fine."""
    trusted = trusted_uids()
    whom = f"not by {trusted_users_phrase()}; rtloop will not talk to it"
    current = path
    try:
        for _ in range(40):  # the kernel's own limit of links followed
            facts = os.lstat(current)
            if not stat.S_ISLNK(facts.st_mode):
                break
            if facts.st_uid not in trusted:
                return f"{current} is a symbolic link owned by uid {facts.st_uid}, {whom}"
            current = os.path.join(os.path.dirname(current), os.readlink(current))
        node = opened or os.stat(path)
    except OSError as error:
        return f"{current}: cannot follow it ({error.strerror}); it changed while rtloop looked"
    if node.st_uid not in trusted:
        return f"{os.path.realpath(path)} is owned by uid {node.st_uid}, {whom}"
    return None


class SerialDevice(Device):
    """A device answering one framed request per cycle on a serial line (see the module)."""

    kind = "serial"
    safe_write_is_exchange = True  # the safe values are a request the device answers
    settings: ClassVar[dict[str, Setting]] = {
        "port": Setting(str, doc="the serial device, e.g. /dev/ttyUSB0 or /dev/ttyAMA0", is_path=True),
        "baudrate": Setting(int, 115200, "bits per second", check=positive,
                            at_most=100_000_000),
        "timeout_ms": Setting(float, 5.0, "how long to wait for the response, in ms (a late one is a fault)",
                              check=positive, at_most=HOUR_MS),
        "commands": Setting(list, doc="names of the values sent each cycle (its u), e.g. [\"voltage_V\"]",
                            check=_names),
        "readings": Setting(list, doc="names of the values received each cycle (its y)", check=_names),
        "on_missing": Setting(str, "fault", "an answer not whole and good within timeout_ms: \"fault\" (stop, "
                              "safe values) or \"stale\" (keep the last readings, count)", check=_on_missing),
        "max_stale_in_a_row": Setting(int, 10, "with on_missing = \"stale\": this many exchanges in a row "
                                      "without a good answer are a fault", check=_at_least_one),
    }

    def __init__(self, name: str, **settings: Any) -> None:
        super().__init__(name, **settings)
        commands, readings = settings["commands"], settings["readings"]
        for key, names in (("commands", commands), ("readings", readings)):
            if len(names) > MAX_VALUES:
                raise DeviceError(name, "", key, f"{len(names)} values; a frame carries at most {MAX_VALUES}")
        self.n_inputs, self.n_outputs = len(commands), len(readings)
        self.input_names, self.output_names = tuple(commands), tuple(readings)
        self.timeout_ns = round(settings["timeout_ms"] * 1e6)
        defaults = {key: setting.default for key, setting in self.settings.items() if not setting.required}
        settings = {**defaults, **settings}  # built directly in Python, not through an app file
        self.on_missing: str = settings["on_missing"]
        self.max_stale_in_a_row: int = settings["max_stale_in_a_row"]
        self.stale_in_a_row = 0
        self.stale_by_source = [0] * len(STALE_SOURCES)
        self._line: Any = None

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_line": None}  # an open port never travels

    def check(self) -> None:
        path = self.config["port"]
        if "://" in path:
            raise DeviceError(self.name, "", "port", f"{path!r}: give the device's path (pyserial URLs are "
                              "not serial lines)")
        try:
            status = os.stat(path)
        except FileNotFoundError:
            raise DeviceError(self.name, "", "port", f"{path} does not exist (is the adapter plugged in? "
                              "rtloop io list shows the serial devices)") from None
        except PermissionError:
            raise DeviceError(self.name, "", "port", f"{path}: no permission to look at it") from None
        if not stat.S_ISCHR(status.st_mode):
            raise DeviceError(self.name, "", "port", f"{path} is not a character device (a serial line)")
        foreign = foreign_owner(path)
        if foreign:
            raise DeviceError(self.name, "", "port", foreign)
        if not os.access(path, os.R_OK | os.W_OK):
            try:
                group = grp.getgrgid(status.st_gid).gr_name
            except KeyError:
                group = str(status.st_gid)
            mode = stat.filemode(status.st_mode)
            raise DeviceError(self.name, "", "port", f"{path}: no permission to open it ({mode}, group {group}); "
                              f"add yourself to that group: sudo usermod -aG {group} $USER, then log in again")
        try:
            import serial  # noqa: F401 - pyserial
        except ImportError:
            raise DeviceError(self.name, "", "kind", "needs pyserial: pip install 'rtloop[serial]'") from None

    def configure(self) -> None:
        import serial

        try:
            self._line = serial.Serial(self.config["port"], self.config["baudrate"], timeout=0, write_timeout=0,
                                       exclusive=True)
        except (serial.SerialException, OSError, ValueError) as error:
            raise DeviceError(self.name, "", "port", f"cannot open {self.config['port']}: {error}") from None
        foreign = foreign_owner(self.config["port"], os.fstat(self._line.fileno()))  # the node opened
        if foreign:
            self._line.close()
            raise DeviceError(self.name, "", "port", foreign)
        self._line.reset_input_buffer()  # nothing left over from before counts as an answer
        self.fd = self._line.fileno()
        self.poller = select.poll()
        self.poller.register(self.fd, select.POLLIN)
        self.request = Frame(REQUEST_SYNC, self.n_inputs)
        self.response = Frame(RESPONSE_SYNC, self.n_outputs)
        self.readings = np.zeros(self.n_outputs)
        self.sequence = 0
        self.requests = 0  # counted from 1, for messages; the frame carries it modulo 256 (its sequence)
        self.exchanges = 0
        self.flags = 0  # not enabled until T0

    def activate(self) -> None:
        self.flags = ENABLED

    def write(self, u: FloatVector) -> None:
        """One exchange: send the commands, wait for the readings (at most ``timeout_ms``)."""
        try:
            self._exchange(u)
        except (OSError, EOFError, termios.error) as error:
            raise self._line_gone(error) from None

    def _line_gone(self, error: BaseException) -> DeviceFault:
        """The fault for a line that failed under the exchange: the board reset, the cable or the
        USB adapter pulled, the other end of a pty closed."""
        code = error.args[0] if error.args and isinstance(error.args[0], int) else None
        reason = os.strerror(code) if code else str(error)
        return DeviceFault(f"device {self.name!r}: {self.config['port']} hung up at {self._request()} "
                           f"({reason}: the other end closed, or the adapter was unplugged)")

    def _exchange(self, u: FloatVector) -> None:
        if self.stale_in_a_row:  # the last exchange went unanswered: its answer, or part of it, may be here
            termios.tcflush(self.fd, termios.TCIFLUSH)
        sequence = self._send(u)
        if self.on_missing == "fault":
            if not read_frame(self.fd, self.response, self.poller, self.timeout_ns):
                raise DeviceFault(f"device {self.name!r}: no response within {self.timeout_ns / 1e6:g} ms "
                                  f"on {self.config['port']} ({self._request()}); on_missing = \"stale\" "
                                  "keeps the last readings instead (a slow line, or a loaded machine)")
            self._take_response(sequence)
            return
        missing = self._await_answer(sequence, self.timeout_ns)
        if missing < 0:
            self._take_response(sequence)
            self.stale_in_a_row = 0
            return
        self.stale_reads += 1  # the readings of the last good answer stay
        self.stale_by_source[missing] += 1
        self.stale_in_a_row += 1
        if self.stale_in_a_row >= self.max_stale_in_a_row:
            raise DeviceFault(f"device {self.name!r}: no good answer to "
                              f"{counted(self.stale_in_a_row, 'request')} in a row "
                              f"on {self.config['port']} (the last: {STALE_SOURCES[missing]}, {self._request()}; "
                              f"max_stale_in_a_row = {self.max_stale_in_a_row})")

    def _await_answer(self, sequence: int, timeout_ns: int) -> int:
        """Wait for the answer to request ``sequence``, passing over whole answers to earlier
        requests: -1 when it came, else why not (an index of ``STALE_SOURCES``)."""
        response = self.response
        deadline_ns = time.monotonic_ns() + timeout_ns
        while True:
            left_ns = deadline_ns - time.monotonic_ns()
            if left_ns <= 0 or not read_frame(self.fd, response, self.poller, left_ns):
                return 0
            if response.problem() is not None:
                return 1  # garbled or cut: the next exchange flushes the rest
            if response.sequence == sequence:
                return -1

    def write_safe(self, u: FloatVector) -> None:
        """The safe values, with outputs no longer enabled: the device may stop watching its heartbeat.

        Often called after an exchange failed: the late answer to that request may be in the
        input buffer or still on the way. It is not this exchange's answer: the input is
        flushed first, and whole answers to earlier requests are passed over until this
        request's own answer (or the timeout: ``timeout_ms``, at least 100 ms, as this is not
        the loop), so the safe state is reported as it went.
        """
        self.flags = 0
        try:
            termios.tcflush(self.fd, termios.TCIFLUSH)
            sequence = self._send(u)
            timeout_ns = max(self.timeout_ns, SAFE_EXCHANGE_MIN_NS)
            missing = self._await_answer(sequence, timeout_ns)
        except (OSError, EOFError, termios.error) as error:
            raise self._line_gone(error) from None
        if missing == 0:
            raise DeviceFault(f"device {self.name!r}: no answer to the safe values within "
                              f"{timeout_ns / 1e6:g} ms on {self.config['port']} ({self._request()})")
        self.stale_in_a_row = 0
        self._take_response(sequence)

    def may_read_stale(self) -> bool:
        return self.on_missing == "stale"

    def stale_sources(self) -> dict[str, int]:
        return {source: count for source, count in zip(STALE_SOURCES, self.stale_by_source, strict=True) if count}

    def _request(self) -> str:
        return f"request {self.requests} (sequence {self.sequence})"

    def _send(self, u: FloatVector) -> int:
        request = self.request
        self.requests += 1
        self.sequence = sequence = (self.sequence + 1) & 0xFF
        request.values[:] = u
        request.seal(sequence, self.flags)
        os.write(self.fd, request.buffer)
        return sequence

    def _take_response(self, sequence: int) -> None:
        response = self.response
        problem = response.problem(sequence)
        if problem is not None:
            raise DeviceFault(f"device {self.name!r}: bad response on {self.config['port']}: {problem}")
        self.readings[:] = response.values
        self.exchanges += 1
        if self.flags and not response.buffer[3] & ENABLED:
            raise DeviceFault(f"device {self.name!r} turned its output off by itself (its heartbeat timed out, "
                              "or it faulted): the app stops")

    def read(self, y: FloatVector) -> None:
        y[:] = self.readings

    def close(self) -> None:
        if self._line is not None:
            self._line.close()
            self._line = None
