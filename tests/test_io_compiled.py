"""The devices' per-cycle work in C (``io/_devio.c``) gives the Python references' numbers bit for bit:
the guard (copies, non-finite check, clamp, rate limit), frame layouts (rounding, saturation, byte
orders, every type), the CAN drain (newest copy of each id, strays counted), a CAN device's whole
cycle (frames sent, heartbeat, readings, waits, stale counts, faults, send errors), GPIO's lines (bits
packed and unpacked, the E-stop's edge) and SPI's frame (counter, CRC, checks, counts, errors)."""

from __future__ import annotations

import binascii
import fcntl
import math
import os
import socket
import struct
import termios
import threading

import numpy as np
import pytest

from can_pair import attach_to_a_pair, wire_frame
from conftest import layout_twins
from io_guest_devices import KEPT_BYTES_ALLOWED, bytes_kept_by
from rtloop.io.bytelayout import Field
from rtloop.io.device import CommandLimit
from rtloop.io.host import DeviceWiring, TaskDevices

devio = pytest.importorskip("rtloop.io._devio", reason="the devices' C part was not built (no compiler)")


TYPES = ["u8", "i8", "u16", "i16", "u32", "i32", "u64", "i64", "f32", "f64"]
VALUES = [0.0, -0.0, 0.5, 1.5, 2.5, -0.5, -1.5, 0.49999999999999994, 1e-300, 123.456, -123.456, 127.5, 128.0,
          -128.5, 255.5, 256.0, 32767.5, -32768.5, 65535.4, 65536.0, 2.0**31, -(2.0**31) - 1, 2.0**32, 2.0**53 + 2,
          2.0**63, -(2.0**63), 2.0**64, 1.8446744073709552e19, -1e30, 1e30, 3.4028235e38, 3.5e38, -3.5e38, 1e308]


@pytest.mark.parametrize("kind", TYPES)
@pytest.mark.parametrize("order", ["little", "big"])
def test_packing_and_unpacking_are_the_references_bit_for_bit(kind, order, monkeypatch):
    fields = [Field("a", 0, kind, 1.0, 0.0, order), Field("b", 8, kind, 0.01, -3.0, order)]
    compiled, reference = layout_twins(fields, 16, monkeypatch)
    for value in VALUES:
        values = np.array([value, value / 7])
        ours, theirs = bytearray(16), bytearray(16)
        errors = []
        for layout, frame in ((compiled, ours), (reference, theirs)):
            try:
                layout.pack_into(frame, 0, memoryview(values))  # as a driver hands them (io/bytelayout.py FloatView)
                errors.append(None)
            except ValueError as error:
                errors.append(str(error))
        assert errors[0] == errors[1], (kind, order, value)
        assert ours == theirs, (kind, order, value)
        back_ours, back_theirs = np.zeros(2), np.zeros(2)
        compiled.unpack_from(ours, 0, back_ours)
        reference.unpack_from(theirs, 0, back_theirs)
        assert back_ours.tobytes() == back_theirs.tobytes(), (kind, order, value)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_value_is_refused_by_both_naming_the_field(bad, monkeypatch):
    compiled, reference = layout_twins([Field("torque", 2, "i16"), Field("speed", 4, "f32")], 8, monkeypatch)
    for index in (0, 1):
        values = np.array([1.0, 2.0])
        values[index] = bad
        messages = []
        for layout in (compiled, reference):
            with pytest.raises(ValueError) as caught:
                layout.pack_into(bytearray(8), 0, memoryview(values))
            messages.append(str(caught.value))
        assert messages[0] == messages[1]
        assert ("'torque'" if index == 0 else "'speed'") in messages[0] and "never sent" in messages[0]


def test_packing_from_an_offset_and_into_a_memoryview(monkeypatch):
    compiled, reference = layout_twins([Field("x", 0, "i32", 1e-3, 0.0, "big")], 4, monkeypatch)
    vector = np.array([9.0, -1.2345, 7.0])
    ours, theirs = bytearray(12), bytearray(12)
    compiled.pack_into(ours, 8, memoryview(vector), 1)
    reference.pack_into(theirs, 8, memoryview(vector), 1)
    assert ours == theirs and struct.unpack(">i", ours[8:]) == (-1234,)
    with pytest.raises(ValueError, match="shorter"):
        compiled.pack_into(bytearray(6), 4, vector, 0)


def task_devices(monkeypatch, compiled: bool, limits, commands, readings, task_u, task_y):
    from device_test_drivers import LogDevice

    if not compiled:
        monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
    device = LogDevice("dev", log="/dev/null", n_commands=len(limits), n_readings=2)
    devices = TaskDevices("ctl", 1_000_000, [DeviceWiring(device, "let", tuple(limits), commands, readings)],
                          task_u, task_y)
    monkeypatch.delenv("RTLOOP_PURE_PYTHON", raising=False)
    assert (devices.slots[0].compiled_guard is not None) == compiled
    return devices


def test_the_guard_and_the_copies_are_the_references_bit_for_bit(monkeypatch):
    limits = [CommandLimit(-1.0, 1.0, 0.0, 250.0), CommandLimit(-5.0, 5.0, 0.5), CommandLimit(0.0, 1e9, 3.0, 1e6)]
    commands = ((slice(1, 4), slice(0, 3)),)
    readings = ((slice(0, 2), slice(2, 4)),)
    rng = np.random.default_rng(7)
    runs = []
    for compiled in (True, False):
        task_u, task_y = np.zeros(4), np.zeros(5)
        devices = task_devices(monkeypatch, compiled, limits, commands, readings, task_u, task_y)
        slot = devices.slots[0]
        written, seen = [], []
        slot.device.write = lambda u, written=written: written.append(u.tobytes())  # what reached the "wire"
        slot.device.read = lambda y: y.__setitem__(slice(None), [1.25, -3.5])
        rng = np.random.default_rng(7)
        for cycle in range(500):
            task_y[:] = rng.normal(0, 3, 5) * rng.choice([1e-3, 1, 1e3], 5)
            devices.at_release(cycle)
            seen.append(task_u.tobytes())
        counted = (slot.guard.clamped.tolist(), slot.guard.rate_limited_cycles.tolist())
        runs.append((written, seen, counted))
    assert runs[0] == runs[1]
    assert len(set(runs[0][0])) > 400  # the commands moved (clamped and rate limited, not stuck)
    clamped, rate_limited = runs[0][2]
    assert all(clamped) and rate_limited[0] > 0 and rate_limited[1] == 0  # counted alike; no rate, no count


def test_a_non_finite_command_is_the_same_fault_either_way(monkeypatch):
    from rtloop.errors import DeviceFault

    limits = [CommandLimit(-1.0, 1.0, 0.0), CommandLimit(-1.0, 1.0, 0.0)]
    messages = []
    for compiled in (True, False):
        task_u, task_y = np.zeros(2), np.array([0.5, math.nan])
        devices = task_devices(monkeypatch, compiled, limits, ((slice(0, 2), slice(0, 2)),), (), task_u, task_y)
        devices.slots[0].device.write = lambda u: pytest.fail(f"a non-finite command reached the device: {u}")
        with pytest.raises(DeviceFault) as caught:
            devices.at_release(41)
        messages.append(str(caught.value))
    assert messages[0] == messages[1] and "cycle 41: dev.u[1] (c1): command nan is not finite" in messages[0]


def test_the_can_drain_keeps_the_newest_of_each_id_and_counts_strays(monkeypatch):
    from rtloop.io.canframes import frame_from_table
    from rtloop.io.cansocket import CanSocket

    frames = [frame_from_table({"id": 0x180, "timeout_ms": 5, "signals": [{"name": "a", "start_byte": 0}]},
                               "receive[0]", False, receive=True),
              frame_from_table({"id": 0x181, "timeout_ms": 5, "signals": [{"name": "b", "start_byte": 0}]},
                               "receive[1]", False, receive=True)]
    results = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
        ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        receiver = CanSocket("pair", False, frames, "devices.drive", sock=ours)
        monkeypatch.delenv("RTLOOP_PURE_PYTHON", raising=False)
        assert (receiver._receiver is not None) == compiled
        for can_id, value in ((0x180, 1), (0x181, 2), (0x180, 3), (0x222, 4)):
            peer.send(struct.pack("=IB3x8s", can_id, 8, struct.pack("<q", value)))
        peer.send(struct.pack("=IB3x64s", 0x181, 64, bytes(64)))  # an FD frame where a classic one was declared
        receiver.receive_cycle(0)
        results.append((list(receiver.fresh), [bytes(b) for b in receiver.latest], receiver.unexpected))
        receiver.close()
        peer.close()
    assert results[0] == results[1]
    fresh, latest, unexpected = results[0]
    assert fresh == [True, True] and struct.unpack_from("<q", latest[0], 8) == (3,) and unexpected == 2


def test_a_build_that_fails_halfway_lets_go_of_every_buffer_it_held():
    """Each C type's init unwinds through one path: whatever failed, the vectors and frame buffers
    it had taken are released (their reference counts are back; a bytearray can be resized again)."""
    import sys

    vectors = [np.zeros(3) for _ in range(6)]
    counters = [np.zeros(3, dtype=np.int64) for _ in range(2)]  # clamped, rate-limited cycles
    source, target, short = np.zeros(2), np.zeros(2), np.zeros(1)
    read_only = np.zeros(2)
    read_only.flags.writeable = False
    everything = [*vectors, *counters, source, target, short, read_only]
    counts = [sys.getrefcount(v) for v in everything]
    failures = [
        (lambda: devio.Guard(*vectors[:5], np.zeros(2), *counters, [], False), "differ in length"),  # all eight held
        (lambda: devio.Guard(*vectors, counters[0], np.zeros(3), [], False), "int64"),
        (lambda: devio.Guard(*vectors, *counters, [(source, target), (source, short)], False), "differ in length"),
        (lambda: devio.Guard(*vectors, *counters, [(source, target), (source, read_only)], False),
         "read-only|writable"),
        (lambda: devio.Copies([(source, target), (source, short)]), "differ in length"),
        (lambda: devio.Copies([(source, read_only)]), "read-only|writable"),
    ]
    for build, message in failures:
        with pytest.raises((ValueError, TypeError, BufferError), match=message):
            build()
        assert [sys.getrefcount(v) for v in everything] == counts, message
    first, too_big = bytearray(16), bytearray(80)
    with pytest.raises(ValueError, match="larger than a CAN FD frame"):
        devio.CanReceiver(-1, [0x100, 0x101], [first, too_big], [False, False])
    first.extend(b"x")  # resizable: no buffer of it is still exported
    with pytest.raises(ValueError, match="unknown field code"):
        devio.Layout([("h", 0, 1.0, 0.0, False), ("z", 2, 1.0, 0.0, False)])



# --- GPIO: GpioLines against GpioDevice's Python write/read ----------------------------------------
# No GPIO chip here: the cycle is built on stand-in fds (GpioDevice._build_cycle takes any). A pty's
# window size is 8 bytes, as the 64 value bits of struct gpio_v2_line_values: TIOCSWINSZ in place of
# SET_VALUES keeps the bits a write packed, TIOCGWINSZ in place of GET_VALUES hands a read the bits
# set before. Both paths make that same ioctl; tests/test_io_gpio.py runs them on gpio-sim lines
# in the guest.
def gpio_pair(monkeypatch, out_bits, in_bits, estop_fd=-1):
    """The same GPIO device twice on one pty: with the C cycle, and the Python reference."""
    from rtloop.io import gpio as gpio_module
    from rtloop.io.device import build_device

    monkeypatch.setattr(gpio_module, "GPIO_V2_LINE_SET_VALUES_IOCTL", termios.TIOCSWINSZ)
    monkeypatch.setattr(gpio_module, "GPIO_V2_LINE_GET_VALUES_IOCTL", termios.TIOCGWINSZ)
    master, slave = os.openpty()
    os.close(slave)
    pair = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
        settings = {"chip": "gpiochip0", "outputs": [f"o{i}" for i in range(len(out_bits))],
                    "inputs": [f"i{i}" for i in range(len(in_bits))], **({"estop": "stop"} if estop_fd >= 0 else {})}
        device = build_device("gpio", "panel", settings, "app.toml")
        device._build_cycle(master, list(out_bits), master, list(in_bits), estop_fd)
        monkeypatch.delenv("RTLOOP_PURE_PYTHON", raising=False)
        assert (device._lines is not None) == compiled
        pair.append(device)
    return pair, master


def line_bits(fd: int) -> int:
    """The 64 bits the last write left on the stand-in."""
    return struct.unpack("=Q", fcntl.ioctl(fd, termios.TIOCGWINSZ, bytes(8)))[0]


def set_line_bits(fd: int, bits: int) -> None:
    fcntl.ioctl(fd, termios.TIOCSWINSZ, struct.pack("=Q", bits))


GPIO_COMMANDS = [0.0, -0.0, 0.5, 0.49999999999999994, 1.0, -1.0, math.nan, -math.nan, math.inf, -math.inf, 1e308,
                 5e-324, 0.75, 0.25]


def test_gpio_writes_and_reads_the_references_bits(monkeypatch):
    out_bits, in_bits = [5, 0, 63, 17, 32], [63, 0, 31, 32, 7]
    (ours, theirs), fd = gpio_pair(monkeypatch, out_bits, in_bits)
    try:
        rng = np.random.default_rng(21)
        for _ in range(300):
            u = rng.choice(GPIO_COMMANDS, len(out_bits))
            written = []
            for device in (ours, theirs):
                set_line_bits(fd, 0)
                device.write(u)
                written.append(line_bits(fd))
            assert written[0] == written[1], u
            assert written[0] == sum(1 << bit for bit, value in zip(out_bits, u, strict=True) if value >= 0.5), u
            pattern = int(rng.integers(0, 2**62)) << 2 | int(rng.integers(0, 4))
            read = []
            for device in (ours, theirs):
                set_line_bits(fd, pattern)
                y = np.full(len(in_bits), 7.0)
                device.read(y)
                read.append(y.tobytes())
            assert read[0] == read[1]
            assert np.frombuffer(read[0]).tolist() == [float(pattern >> bit & 1) for bit in in_bits]
        set_line_bits(fd, 0)
        ours.write([1, 0, 1, 0, 1])  # not a float64 vector: the Python way, the same bits
        assert line_bits(fd) == 1 << 5 | 1 << 63 | 1 << 32
    finally:
        for device in (ours, theirs):
            device.close()
        os.close(fd)


def test_gpio_errors_are_the_references(monkeypatch):
    (ours, theirs), fd = gpio_pair(monkeypatch, [1, 2], [3])
    try:
        for call, vector in (("write", np.zeros(1)), ("read", np.zeros(0))):  # shorter than the lines
            for device in (ours, theirs):
                with pytest.raises(IndexError):
                    getattr(device, call)(vector)
        null = os.open("/dev/null", os.O_RDWR)  # a file that is no line request: the kernel refuses the ioctl
        try:
            for device in (ours, theirs):
                device._build_cycle(null, [1, 2], null, [3], -1)
            errors = []
            for device in (ours, theirs):
                for call in (device.write, device.read):
                    with pytest.raises(OSError) as caught:
                        call(np.zeros(2))
                    errors.append((type(caught.value), caught.value.errno, caught.value.strerror))
            assert errors[:2] == errors[2:] and errors[0][1] == 25  # ENOTTY, as fcntl.ioctl reports it
        finally:
            for device in (ours, theirs):
                device.close()
            os.close(null)
    finally:
        os.close(fd)


def test_a_pending_estop_edge_stops_both_before_the_inputs_are_read(monkeypatch):
    from rtloop.io.gpio import EmergencyStop
    from rtloop.io.kernel import GPIO_V2_LINE_EVENT, GPIO_V2_LINE_EVENT_FALLING_EDGE

    edges, edge_in = os.pipe()  # the E-stop request's fd: readable when the kernel queued an edge
    (ours, theirs), fd = gpio_pair(monkeypatch, [0], [0], estop_fd=edges)
    try:
        stops = []
        for device in (ours, theirs):
            set_line_bits(fd, 1)
            y = np.zeros(1)
            device.read(y)  # nothing queued: the inputs are read
            assert y[0] == 1.0
            os.write(edge_in, GPIO_V2_LINE_EVENT.pack(123_456_789, GPIO_V2_LINE_EVENT_FALLING_EDGE, 4, 1, 1))
            y[0] = 7.0
            with pytest.raises(EmergencyStop) as stop:
                device.read(y)
            assert y[0] == 7.0  # stopped before reading
            stops.append((str(stop.value), stop.value.to_json()))
        assert stops[0] == stops[1]
        assert stops[0][1] == {"device": "panel", "line": "stop", "edge": "falling", "edge_ns": 123_456_789}
    finally:
        for device in (ours, theirs):
            device.close()
        os.close(fd)
        os.close(edges)
        os.close(edge_in)


# --- SPI: SpiFrame against SpiDevice's Python cycle and io/spiframe.py ------------------------------
# No spidev here: the frames are built without a device (SpiDevice._build_frames), and a transfer is
# played in its two halves around the ioctl: seal (counter, CRC), the device's answer put in the
# receive frame by the test, check (CRC, counter, counts). The guest's tests/test_io_spi.py runs the
# whole cycle on the loopback controller.
SPI_SIGNALS = [{"name": "pwm", "start_byte": 1, "type": "i16", "scale": 0.001},
               {"name": "on", "start_byte": 3, "type": "u8"},
               {"name": "speed", "start_byte": 4, "type": "f32", "byte_order": "big", "offset": -2.5}]


def spi_pair(monkeypatch, counter="previous", on_error="fault", fd=-1):
    """The same SPI device twice, frames built: with the C cycle, and the Python reference."""
    from rtloop.io.device import build_device

    pair = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
        device = build_device("spi", "fpga", {"device": "/dev/spidev0.0", "length": 10, "send": SPI_SIGNALS,
                                              "receive": SPI_SIGNALS, "counter": counter, "on_error": on_error},
                              "app.toml")
        device.fd = fd
        device._build_frames()
        monkeypatch.delenv("RTLOOP_PURE_PYTHON", raising=False)
        assert (device._frame is not None) == compiled
        pair.append(device)
    return pair


def spi_state(device):
    """What the frame check knows, from either path."""
    frame, check = device._frame, device._check
    if frame is not None:
        return frame.counter, frame.expected, frame.bad_crc, frame.bad_counter, frame.last_error
    return device._counter, check.expected, check.bad_crc, check.bad_counter, check.last_error


def answer_from(rng, sent: bytes, previous: int, counter: str) -> bytes:
    """A device's answer: good (this frame's counter, or the one before), or spoiled in one of the ways
    a bus spoils it."""
    from rtloop.io.spiframe import crc16_ccitt

    frame = bytearray(rng.integers(0, 256, len(sent), dtype=np.uint8).tobytes())
    frame[0] = sent[0] if counter == "echo" else previous & 0xFF
    way = rng.integers(0, 6)
    if way == 1:  # a counter off by some
        frame[0] = (frame[0] + int(rng.integers(1, 256))) & 0xFF
    crc = crc16_ccitt(frame[:-2])
    frame[-2:] = crc.to_bytes(2, "big")
    if way == 2:  # a bit flipped on the wire
        bit = int(rng.integers(0, 8 * len(frame)))
        frame[bit // 8] ^= 1 << bit % 8
    elif way == 3:  # nobody listening: the line floats high
        frame = bytearray(b"\xff" * len(frame))
    elif way == 4:
        frame = bytearray(len(frame))
    return bytes(frame)


@pytest.mark.parametrize("counter", ["previous", "echo"])
@pytest.mark.parametrize("on_error", ["fault", "stale"])
def test_spi_frames_checks_counts_and_errors_are_the_references(counter, on_error, monkeypatch):
    from rtloop.errors import DeviceFault

    ours, theirs = spi_pair(monkeypatch, counter, on_error)
    rng = np.random.default_rng(5)
    answers = np.random.default_rng(6)
    valid_seen = set()
    for cycle in range(600):  # the counter wraps at 256
        u = np.array([rng.normal(0, 40), rng.integers(0, 300), rng.normal(0, 1e3)])
        answer = None
        results = []
        for device in (ours, theirs):
            device.tx_layout.pack_into(device._tx, 0, memoryview(u))
            if device._frame is not None:
                device._frame.seal()
            else:
                device._seal_frame()
            sent = bytes(device._tx)
            if answer is None:
                answer = answer_from(answers, sent, cycle - 1, counter)
            device._rx[:] = answer
            valid = device._frame.check() if device._frame is not None else device._check_answer()
            y = np.full(3, 7.0)
            try:
                device.read(y)  # fresh after the transfer: checks and unpacks, no second transfer
                error = None
            except DeviceFault as fault:
                error = str(fault)
            results.append((sent, valid, spi_state(device), y.tobytes(), error, device.stale_reads,
                            device.transfers_rejected))
        assert results[0] == results[1], (cycle, results)
        valid_seen.add(results[0][1])
        assert struct.unpack(">H", results[0][0][-2:])[0] == binascii.crc_hqx(results[0][0][:-2], 0xFFFF)
    assert valid_seen == {True, False}
    assert ours._frame.bad_crc > 50 and ours._frame.bad_counter > 50


def test_spi_a_non_finite_command_is_the_same_error_and_nothing_goes_out(monkeypatch):
    null = os.open("/dev/null", os.O_RDWR)  # any transfer would fail on it: none may be tried
    try:
        ours, theirs = spi_pair(monkeypatch, fd=null)
        messages = []
        for device in (ours, theirs):
            before = bytes(device._tx)
            with pytest.raises(ValueError) as caught:
                device.write(np.array([1.0, math.nan, 2.0]))
            messages.append(str(caught.value))
            assert bytes(device._tx)[3:] == before[3:] and spi_state(device)[0] == 0
        assert messages[0] == messages[1] and "'on' is nan" in messages[0]
    finally:
        os.close(null)


def test_spi_a_refused_transfer_is_the_same_oserror_and_moves_nothing(monkeypatch):
    null = os.open("/dev/null", os.O_RDWR)  # not an SPI device: the kernel refuses SPI_IOC_MESSAGE
    try:
        ours, theirs = spi_pair(monkeypatch, counter="echo", fd=null)
        outcomes = []
        for device in (ours, theirs):
            errors = []
            for call, vector in ((device.write, np.array([0.5, 1.0, 2.0])), (device.read, np.zeros(3)),
                                 (device.write, [0.5, 1, 2])):  # a list: packed in Python, transferred the same way
                with pytest.raises(OSError) as caught:
                    call(vector)
                errors.append((type(caught.value), caught.value.errno, caught.value.strerror))
            outcomes.append((errors, bytes(device._tx), spi_state(device)))
        assert outcomes[0] == outcomes[1]
        assert outcomes[0][0][0][1] == 25 and outcomes[0][2][0] == 0  # ENOTTY; the counter did not move
    finally:
        os.close(null)


def test_the_crc_in_c_is_crc16_ccitt_false():
    from rtloop.io.spiframe import crc16_ccitt

    assert devio.crc16_ccitt(b"123456789") == 0x29B1 == crc16_ccitt(b"123456789")
    rng = np.random.default_rng(3)
    for size in (0, 1, 2, 7, 64, 4094):
        data = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        assert devio.crc16_ccitt(data) == binascii.crc_hqx(data, 0xFFFF)


def test_an_spi_frame_refuses_a_transfer_that_does_not_point_at_its_frames():
    from rtloop.io.kernel import SPI_IOC_MESSAGE_1, SPI_IOC_TRANSFER, address_of

    tx, rx, elsewhere = bytearray(8), bytearray(8), bytearray(8)
    layout = devio.Layout([("h", 1, 1.0, 0.0, False)])
    pins = [address_of(buffer) for buffer in (tx, rx, elsewhere)]
    for tx_address, rx_address, length in ((pins[0][0], pins[2][0], 8), (pins[0][0], pins[1][0], 6)):
        transfer = bytearray(SPI_IOC_TRANSFER.pack(tx_address, rx_address, length, 1000, 0, 8, 0, 0, 0, 0, 0))
        with pytest.raises(ValueError, match="not pointing at tx and rx"):
            devio.SpiFrame(-1, SPI_IOC_MESSAGE_1, transfer, tx, rx, layout, layout, True)
    transfer = bytearray(SPI_IOC_TRANSFER.pack(pins[0][0], pins[1][0], 8, 1000, 0, 8, 0, 0, 0, 0, 0))
    with pytest.raises(ValueError, match="no room for the counter and the CRC"):
        devio.SpiFrame(-1, SPI_IOC_MESSAGE_1, transfer, tx, rx, devio.Layout([("i", 4, 1.0, 0.0, False)]), layout,
                       True)
    frame = devio.SpiFrame(-1, SPI_IOC_MESSAGE_1, transfer, tx, rx, layout, layout, False)
    frame.release()
    with pytest.raises(ValueError, match="released"):
        frame.write(np.zeros(1))


def test_the_gpio_and_spi_cycles_in_c_keep_nothing_allocated(monkeypatch):
    """10,000 cycles of each C cycle under tracemalloc, on the stand-ins above (the guest's
    tests/test_io_gpio.py and test_io_spi.py do the same on the devices)."""

    (lines, _reference), fd = gpio_pair(monkeypatch, [0, 9], [9, 3])
    frame_device, _ = spi_pair(monkeypatch, counter="echo", on_error="stale")
    frame = frame_device._frame
    u, y = np.array([1.0, 0.0]), np.zeros(2)
    signals, readings = np.array([0.25, 1.0, -3.0]), np.zeros(3)
    good, spoiled = [False], bytes(frame_device.length)

    def cycle() -> None:
        u[0] = 1.0 - u[0]
        lines.write(u)
        lines.read(y)
        frame_device.tx_layout.pack_into(frame_device._tx, 0, signals)
        frame.seal()
        good[0] = not good[0]
        frame_device._rx[:] = frame_device._tx if good[0] else spoiled  # good and bad answers by turns
        frame.check()
        frame_device.read(readings)

    try:
        kept = bytes_kept_by(cycle, 10_000)
    finally:
        lines.close()
        _reference.close()
        os.close(fd)
    assert frame_device.stale_reads == 6_000 and frame.bad_crc == 6_000
    assert list(readings) == [0.25, 1.0, -3.0]  # the good answers were unpacked
    assert kept <= KEPT_BYTES_ALLOWED, kept


# --- CAN: CanCycle against CanDevice's Python write/read -----------------------------------------
# A UNIX socket pair stands in for the CAN socket (this kernel may have no CAN): the same send, poll
# and recv calls; the peer plays the bus. tests/test_io_can.py runs the C cycle on vcan0 in the guest.
CAN_SEND = [{"id": 0x200, "signals": [{"name": "torque", "start_byte": 0, "type": "i16", "scale": 0.01},
                                      {"name": "mode", "start_byte": 2, "type": "u8"},
                                      {"name": "gain", "start_byte": 4, "type": "f32", "byte_order": "big"}]},
            {"id": 0x1ABCDE, "extended": True, "signals": [{"name": "speed", "start_byte": 0, "type": "i32",
                                                            "scale": 1e-3, "offset": 2.0}]}]
CAN_RECEIVE = [{"id": 0x180, "timeout_ms": 2, "signals": [{"name": "position", "start_byte": 0, "type": "i32",
                                                          "scale": 1e-4}]},
               {"id": 0x181, "timeout_ms": 1, "on_missing": "stale",
                "signals": [{"name": "current", "start_byte": 0, "type": "i16", "scale": 0.01, "byte_order": "big"},
                            {"name": "temp", "start_byte": 2, "type": "u8"}]},
               {"id": 0x1ABC00, "extended": True, "timeout_ms": 1.5, "on_missing": "stale",
                "signals": [{"name": "volts", "start_byte": 0, "type": "f64"}]}]


def can_pair(monkeypatch, fd=False, **settings):
    """The same CAN device twice, each on a socket pair of its own: with the C cycle, and the Python
    reference. Returns [(device, peer), (device, peer)]."""
    from rtloop.io.device import build_device

    pair = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
        table = {"interface": "pair", "fd": fd, "send": CAN_SEND, "receive": CAN_RECEIVE, "heartbeat": {"id": 0x700},
                 **settings}
        device = build_device("can", "drive", table, "app.toml")
        peer = attach_to_a_pair(device, fd)
        peer.setblocking(False)
        monkeypatch.delenv("RTLOOP_PURE_PYTHON", raising=False)
        assert (device._cycle is not None) == compiled
        pair.append((device, peer))
    return pair


def taken_off(peer) -> list[bytes]:
    """Every frame the device sent since the last call."""
    frames = []
    while True:
        try:
            frames.append(peer.recv(128))
        except BlockingIOError:
            return frames


def can_state(device) -> tuple:
    return (device.stale_reads, list(device.stale_by_frame), device.socket.unexpected, list(device.socket.fresh))


@pytest.mark.parametrize("fd", [False, True])
@pytest.mark.parametrize("order", [(0, 1, 2), (1, 0, 2)])  # the frame that faults first, or between stale ones
def test_can_frames_sent_readings_stale_counts_and_faults_are_the_references(fd, order, monkeypatch):
    from rtloop.errors import DeviceFault

    pair = can_pair(monkeypatch, fd=fd, receive=[CAN_RECEIVE[i] for i in order])
    rng, bus = np.random.default_rng(11), np.random.default_rng(12)
    ids = [(0x180, 0x181, 0x1ABC00 | 0x80000000)[i] for i in order]
    outcomes_seen = set()
    try:
        for cycle in range(300):
            u = np.array([rng.normal(0, 200), rng.integers(0, 300), rng.normal(0, 1e3), rng.normal(0, 1e4)])
            if cycle % 37 == 5:
                u[int(rng.integers(0, 4))] = [math.nan, math.inf, -math.inf, 1e308][cycle % 4]
            # what the bus brings this cycle: each id 0, 1 or 2 times (the newest wins), and strays
            arriving = []
            for can_id in ids:
                for _ in range(int(bus.integers(0, 3)) if cycle % 11 else 1):
                    arriving.append(wire_frame(can_id, bus.integers(0, 256, 8).astype(np.uint8).tobytes(), fd))
            if cycle % 7 == 3:
                arriving.append(wire_frame(0x222, bytes(8), fd))  # an id not declared
                arriving.append(wire_frame(0x181, bytes(8), not fd))  # a declared id of the other size
            results = []
            for device, peer in pair:
                outcome = []
                try:
                    device.write(u)
                    outcome.append(None)
                except ValueError as error:
                    outcome.append(str(error))
                outcome.append(taken_off(peer))
                for wire in arriving:
                    peer.send(wire)
                y = np.full(4, 7.0)
                try:
                    device.read(y)
                    outcome.append(None)
                except DeviceFault as fault:
                    outcome.append(str(fault))
                outcome += [y.tobytes(), can_state(device)]
                results.append(outcome)
            assert results[0] == results[1], (cycle, results)
            outcomes_seen.add((results[0][0] is None, results[0][2] is None))
        assert {(True, True), (True, False), (False, True)} <= outcomes_seen  # sent or refused, read or faulted
        device = pair[0][0]
        assert device.stale_reads > 50 and device.socket.unexpected > 50
        assert all(count > 10 for count, frame in zip(device.stale_by_frame, device.received, strict=True)
                   if frame.on_missing == "stale")
    finally:
        for device, peer in pair:
            device.close()
            peer.close()


def test_can_a_list_goes_the_reference_way_and_the_heartbeat_counts_on(monkeypatch):
    pair = can_pair(monkeypatch, receive=[])
    try:
        sent = []
        for device, peer in pair:
            for u in (np.array([1.0, 2.0, 3.0, 4.0]), [1, 2, 3.0, 4], np.array([0.5, 1.0, 2.0, 3.0]),
                      np.array([0.5, 1.0, 2.0, 3.0, 9.0])):  # longer than u: the first four, the same way
                device.write(u)
            device.read(np.zeros(0))
            frames = taken_off(peer)
            assert [f[8] for f in frames if struct.unpack_from("=I", f)[0] == 0x700] == [0, 1, 2, 3]
            sent.append(frames)
        assert sent[0] == sent[1]
    finally:
        for device, peer in pair:
            device.close()
            peer.close()


def test_can_a_failed_send_is_the_same_device_fault(monkeypatch):
    """A send the bus refuses is a field event (tests/test_io_can_link.py): the same DeviceFault from both."""
    from rtloop.errors import DeviceFault

    pair = can_pair(monkeypatch)
    errors = []
    for device, peer in pair:
        writes = [0]
        try:
            with pytest.raises(DeviceFault) as caught:
                while writes[0] < 100_000:  # nobody takes the frames off: the queue fills
                    device.write(np.array([1.0, 2.0, 3.0, 4.0]))
                    writes[0] += 1
            full = (type(caught.value), str(caught.value), writes[0], len(taken_off(peer)))
            peer.close()
            with pytest.raises(DeviceFault) as caught:
                device.write(np.array([1.0, 2.0, 3.0, 4.0]))
            errors.append((full, type(caught.value), str(caught.value)))
        finally:
            device.close()
            peer.close()
    assert errors[0] == errors[1]
    assert "the transmit queue is full" in errors[0][0][1] and "sending on CAN interface" in errors[0][2]


def test_can_a_frame_is_waited_for_within_its_timeout_counted_from_the_start_of_the_read(monkeypatch):
    """A frame that comes while the read waits is this cycle's; one that has not come by its timeout
    is stale or a fault, as declared, the same either way."""
    from rtloop.errors import DeviceFault

    receive = [{**CAN_RECEIVE[0], "timeout_ms": 3000}, {**CAN_RECEIVE[1], "timeout_ms": 30}]
    pair = can_pair(monkeypatch, receive=receive)
    outcomes = []
    try:
        for device, peer in pair:
            later = threading.Timer(0.1, peer.send, (wire_frame(0x180, struct.pack("<i", 12345), False),))
            later.start()
            y = np.full(3, 7.0)
            device.read(y)  # waits for 0x180 (3 s allowed), 0x181 stays stale
            later.join()
            outcomes.append((y.tobytes(), can_state(device)))
        assert outcomes[0] == outcomes[1]
        assert struct.unpack("=3d", outcomes[0][0])[0] == pytest.approx(1.2345)
        assert outcomes[0][1][:2] == (1, [0, 1])
    finally:
        for device, peer in pair:
            device.close()
            peer.close()
    pair = can_pair(monkeypatch, receive=[{**CAN_RECEIVE[0], "timeout_ms": 20}])
    messages = []
    try:
        for device, peer in pair:
            later = threading.Timer(0.5, peer.send, (wire_frame(0x180, bytes(8), False),))  # after the timeout
            later.start()
            with pytest.raises(DeviceFault) as caught:
                device.read(np.zeros(1))
            later.join()
            messages.append(str(caught.value))
            device.read(np.zeros(1))  # it came late: the next cycle's
    finally:
        for device, peer in pair:
            device.close()
            peer.close()
    assert messages[0] == messages[1] == ('devices.drive.receive[0] (id 0x180): no frame within 20 ms '
                                          '(on_missing = "fault")')


def test_the_can_cycle_in_c_keeps_nothing_allocated(monkeypatch):
    """10,000 cycles of the C cycle: every frame sent, answers fresh and stale by turns."""

    receive = [{**CAN_RECEIVE[0], "timeout_ms": 5000}, {**CAN_RECEIVE[1], "timeout_ms": 0.001}]
    (device, peer), (reference, reference_peer) = can_pair(monkeypatch, receive=receive)
    reference.close()
    reference_peer.close()
    u, y = np.array([1.0, 2.0, 3.0, 4.0]), np.zeros(3)
    answer, stale_too = wire_frame(0x180, struct.pack("<i", 5), False), wire_frame(0x181, bytes(8), False)
    incoming = bytearray(128)
    turn = [0]

    def cycle() -> None:
        turn[0] ^= 1
        device.write(u)
        for _ in range(3):  # two frames and the heartbeat
            peer.recv_into(incoming)
        peer.send(answer)
        if turn[0]:
            peer.send(stale_too)
        device.read(y)

    try:
        kept = bytes_kept_by(cycle, 10_000)
    finally:
        device.close()
        peer.close()
    assert device.stale_reads == 6_000 and y[0] == pytest.approx(5e-4)
    assert kept <= KEPT_BYTES_ALLOWED, kept


def test_a_can_cycle_refuses_frames_that_do_not_fit_and_lets_go_when_released():
    import sys

    ours, peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    latest = [bytearray(16)]
    receiver = devio.CanReceiver(ours.fileno(), [0x180], latest, [False])
    layout, wide = devio.Layout([("h", 0, 1.0, 0.0, False)]), devio.Layout([("q", 4, 1.0, 0.0, False)])
    sent = bytearray(16)
    counts = [sys.getrefcount(x) for x in (receiver, layout, wide, sent)]
    for build, message in (
            (lambda: devio.CanCycle(receiver, [sent], [wide], None, [layout], [1], [True]), "send frame"),
            (lambda: devio.CanCycle(receiver, [sent], [layout], None, [wide], [1], [True]), "shorter"),
            (lambda: devio.CanCycle(receiver, [sent], [layout], None, [], [], []), "differ in length"),
            (lambda: devio.CanCycle(receiver, [sent], [layout], bytearray(4), [layout], [1], [True]), "heartbeat")):
        with pytest.raises(ValueError, match=message):
            build()
        assert [sys.getrefcount(x) for x in (receiver, layout, wide, sent)] == counts, message
    sent.extend(b"x")  # resizable again: no buffer of it is still held
    del sent[16:]
    cycle = devio.CanCycle(receiver, [sent], [layout], None, [layout], [1], [True])
    cycle.release()
    for call, vector in ((cycle.write, np.zeros(1)), (cycle.read, np.zeros(1))):
        with pytest.raises(ValueError, match="released"):
            call(vector)
    assert [sys.getrefcount(x) for x in (receiver, layout, wide)] == counts[:3]
    receiver.release()
    ours.close()
    peer.close()


# --- a build that is not its sources' ------------------------------------------------------------


def test_the_build_carries_the_digest_of_the_sources_it_was_built_from() -> None:
    """setup.py passes the digest; io/compiled.py computes it the same way from the files here."""
    from rtloop.io import compiled

    assert compiled.sources_digest() == devio.SOURCES_DIGEST
    assert "_devio.c" in compiled.source_names() and "devio_c/can.c" in compiled.source_names()


def test_a_build_older_than_its_sources_is_not_used_and_says_so_once() -> None:
    """Before: a stale _devio was used silently (its objects called with arguments they no longer take)."""
    import subprocess
    import sys

    code = ("from rtloop.io import compiled\n"
            "compiled.sources_digest = lambda folder=None: 'changed!'  # the sources changed since the build\n"
            "print(compiled.devio(), compiled.devio())\n"
            "print(compiled.why_python())\n")
    env = {key: value for key, value in os.environ.items() if key != "RTLOOP_PURE_PYTHON"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60, check=True)
    modules, why = done.stdout.splitlines()
    assert modules == "None None"
    assert "built from other sources" in why and "pip install -e ." in why
    said = [line for line in done.stderr.splitlines() if "rtloop.io._devio" in line]
    assert len(said) == 1 and "the Python references run" in said[0], done.stderr


def test_a_compiled_guard_that_refuses_its_arguments_says_so_once(monkeypatch, capsys) -> None:
    """Before: a TypeError from the compiled objects (a build and a Python side that disagree) fell back
    to the numpy path without a word."""
    from device_test_drivers import LogDevice
    from rtloop.io import compiled, host

    class Disagreeing:
        SOURCES_DIGEST = ""

        def Guard(self, *args):
            raise TypeError("Guard() takes 7 arguments (8 given)")

        Copies = Guard

    monkeypatch.setattr(host, "devio", lambda: Disagreeing())
    monkeypatch.setattr(compiled, "_said", set())
    limits = [CommandLimit(-1.0, 1.0, 0.0)]
    for _ in range(2):
        device = LogDevice("dev", log="/dev/null", n_commands=1, n_readings=2)
        wiring = DeviceWiring(device, "let", tuple(limits), ((slice(0, 1), slice(0, 1)),), ())
        devices = TaskDevices("ctl", 1_000_000, [wiring], np.zeros(2), np.zeros(2))
        assert devices.slots[0].compiled_guard is None  # the numpy reference runs
    said = [line for line in capsys.readouterr().err.splitlines() if "refused its arguments" in line]
    assert len(said) == 1 and "device 'dev'" in said[0] and "TypeError" in said[0]
