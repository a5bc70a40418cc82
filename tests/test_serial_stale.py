"""The serial driver's ``on_missing``: an answer that does not come in time is a fault, or (``"stale"``)
the cycle keeps the last readings and counts it; late answers to earlier requests are passed over,
a garbled frame is flushed, and ``max_stale_in_a_row`` unanswered requests are a fault all the same."""

from __future__ import annotations

import os
import tty
from collections.abc import Iterator

import numpy as np
import pytest

from rtloop.errors import DeviceError, DeviceFault
from rtloop.io.device import build_device
from rtloop.io.serial import ENABLED, REQUEST_SYNC, RESPONSE_SYNC, Frame, SerialDevice

pytest.importorskip("serial", reason="pyserial is not installed: pip install 'rtloop[serial]'")

TIMEOUT_MS = 1000.0
"""Time for the board's thread of this test to answer: the request and the answer each pass the pty's kernel
worker and the thread must be scheduled in between; at 30 ms a loaded machine (the suite in two processes
beside a QEMU guest) once scheduled it later, and a garbled answer was counted as a missing one."""
SILENT_MS = 100.0
"""The timeout of an exchange the board leaves unanswered: nothing is to come, so a stall changes nothing
(and each such exchange costs only this long)."""


class Board:
    """The device's end of a pty: reads each request and answers it when the test says."""

    def __init__(self, master: int) -> None:
        self.master = master
        self.request, self.response = Frame(REQUEST_SYNC, 1), Frame(RESPONSE_SYNC, 1)

    def take_request(self) -> int:
        got = os.readv(self.master, [self.request.buffer])
        assert got == len(self.request.buffer) and self.request.problem() is None
        return self.request.sequence

    def answer(self, sequence: int, speed: float) -> None:
        self.response.values[:] = speed
        self.response.seal(sequence, self.request.buffer[3] & ENABLED)
        os.write(self.master, self.response.buffer)


@pytest.fixture
def line() -> Iterator[tuple[str, Board]]:
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        yield os.ttyname(slave), Board(master)
    finally:
        os.close(master)
        os.close(slave)


def _device(port: str, **settings: object) -> SerialDevice:
    device = build_device("serial", "motor", {"port": port, "commands": ["voltage_V"], "readings": ["speed_rad_s"],
                                               "timeout_ms": TIMEOUT_MS, **settings}, "app.toml")
    assert isinstance(device, SerialDevice)
    device.check()
    device.configure()
    device.activate()
    return device


def _exchange(device: SerialDevice, board: Board, speed: float | None, *,
              late: tuple[int, float] | None = None) -> np.ndarray:
    """One cycle: the board answers with ``speed`` (None: not in time), after ``late``'s answer to an
    earlier request if given. The board answers before the driver waits (the pty holds the bytes)."""
    import threading

    def board_side() -> None:
        sequence = board.take_request()
        if late is not None:
            board.answer(*late)
        if speed is not None:
            board.answer(sequence, speed)

    helper = threading.Thread(target=board_side)
    helper.start()
    if speed is None:
        device.timeout_ns = round(SILENT_MS * 1e6)
    try:
        device.write(np.array([1.0]))
    finally:
        device.timeout_ns = round(TIMEOUT_MS * 1e6)
        helper.join()
    readings = np.zeros(1)
    device.read(readings)
    return readings


def test_a_missing_answer_is_a_fault_that_names_the_choice(line: tuple[str, Board]) -> None:
    port, board = line
    device = _device(port)
    assert _exchange(device, board, 5.0)[0] == 5.0
    with pytest.raises(DeviceFault, match=rf"no response within {SILENT_MS:g} ms .*on_missing = \"stale\""):
        _exchange(device, board, None)
    device.close()


def test_stale_keeps_the_last_readings_and_passes_over_the_late_answer(line: tuple[str, Board]) -> None:
    port, board = line
    device = _device(port, on_missing="stale")
    assert device.may_read_stale()
    assert _exchange(device, board, 5.0)[0] == 5.0
    late_sequence = device.sequence + 1
    assert _exchange(device, board, None)[0] == 5.0  # not answered in time: the last readings stay
    assert device.stale_reads == 1
    # the late answer (6.0, to the request before) comes now, then this request's own (7.0)
    assert _exchange(device, board, 7.0, late=(late_sequence, 6.0))[0] == 7.0
    assert device.stale_reads == 1 and device.stale_in_a_row == 0
    assert device.stale_sources() == {"no answer within timeout_ms": 1}
    device.close()


def test_a_garbled_answer_is_stale_and_flushed_before_the_next_exchange(line: tuple[str, Board]) -> None:
    port, board = line
    device = _device(port, on_missing="stale")
    assert _exchange(device, board, 5.0)[0] == 5.0
    import threading

    def garble() -> None:
        board.take_request()
        os.write(board.master, b"\x5a\x08\x00" + bytes(12))  # the right size, a wrong CRC, then a stray byte
        os.write(board.master, b"\x5a")

    helper = threading.Thread(target=garble)
    helper.start()
    device.write(np.array([1.0]))
    helper.join()
    assert device.stale_reads == 1 and device.stale_sources() == {"bad frame (sync, length or CRC)": 1}
    assert _exchange(device, board, 8.0)[0] == 8.0  # the stray byte was flushed: frames line up again
    device.close()


def test_too_many_stale_answers_in_a_row_are_a_fault(line: tuple[str, Board]) -> None:
    port, board = line
    device = _device(port, on_missing="stale", max_stale_in_a_row=3)
    assert _exchange(device, board, 5.0)[0] == 5.0
    _exchange(device, board, None)
    _exchange(device, board, None)
    with pytest.raises(DeviceFault, match=r"no good answer to 3 requests in a row .*max_stale_in_a_row = 3"):
        _exchange(device, board, None)
    device.close()


@pytest.mark.parametrize(("key", "value", "problem"), [
    ("on_missing", "maybe", "expected one of fault, stale, got 'maybe'"),
    ("max_stale_in_a_row", 0, "must be at least 1, got 0"),
])
def test_bad_choices_name_the_key(key: str, value: object, problem: str) -> None:
    with pytest.raises(DeviceError) as caught:
        build_device("serial", "motor", {"port": "/dev/null", "commands": ["v"], "readings": ["s"], key: value},
                     "app.toml")
    assert key in str(caught.value) and problem in str(caught.value)


def test_a_line_that_hangs_up_is_a_fault_naming_the_device_and_the_port(line: tuple[str, Board]) -> None:
    """The board reset, the adapter pulled, the pty's other end closed: one DeviceFault that says so."""
    port, board = line
    device = _device(port, on_missing="stale")
    assert _exchange(device, board, 5.0)[0] == 5.0
    os.close(board.master)
    board.master = os.open("/dev/null", os.O_RDWR)  # the fixture closes something
    with pytest.raises(DeviceFault, match=rf"device 'motor': {port} hung up at request \d+ \(.*unplugged\)"):
        device.write(np.array([1.0]))
    with pytest.raises(DeviceFault, match="hung up"):
        device.write_safe(np.array([0.0]))
    device.close()
