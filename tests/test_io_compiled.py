"""The devices' per-cycle work in C (``io/_devio.c``) gives the Python references' numbers bit for bit:
the guard (copies, non-finite check, clamp, rate limit), frame layouts (rounding, saturation, byte
orders, every type), and the CAN drain (newest copy of each id, strays counted)."""

from __future__ import annotations

import math
import socket
import struct

import numpy as np
import pytest

from rtloop.io.bytelayout import ByteLayout, Field
from rtloop.io.device import CommandLimit
from rtloop.io.host import DeviceWiring, TaskDevices

devio = pytest.importorskip("rtloop.io._devio", reason="the devices' C part was not built (no compiler)")


def layouts(fields, size, monkeypatch):
    """The same layout twice: compiled, and the Python reference."""
    compiled = ByteLayout(fields, size, "frame")
    monkeypatch.setenv("RTLOOP_PURE_PYTHON", "1")
    reference = ByteLayout(fields, size, "frame")
    monkeypatch.delenv("RTLOOP_PURE_PYTHON")
    assert compiled._compiled is not None and reference._compiled is None
    return compiled, reference


TYPES = ["u8", "i8", "u16", "i16", "u32", "i32", "u64", "i64", "f32", "f64"]
VALUES = [0.0, -0.0, 0.5, 1.5, 2.5, -0.5, -1.5, 0.49999999999999994, 1e-300, 123.456, -123.456, 127.5, 128.0,
          -128.5, 255.5, 256.0, 32767.5, -32768.5, 65535.4, 65536.0, 2.0**31, -(2.0**31) - 1, 2.0**32, 2.0**53 + 2,
          2.0**63, -(2.0**63), 2.0**64, 1.8446744073709552e19, -1e30, 1e30, 3.4028235e38, 3.5e38, -3.5e38, 1e308]


@pytest.mark.parametrize("kind", TYPES)
@pytest.mark.parametrize("order", ["little", "big"])
def test_packing_and_unpacking_are_the_references_bit_for_bit(kind, order, monkeypatch):
    fields = [Field("a", 0, kind, 1.0, 0.0, order), Field("b", 8, kind, 0.01, -3.0, order)]
    compiled, reference = layouts(fields, 16, monkeypatch)
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
    compiled, reference = layouts([Field("torque", 2, "i16"), Field("speed", 4, "f32")], 8, monkeypatch)
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
    compiled, reference = layouts([Field("x", 0, "i32", 1e-3, 0.0, "big")], 4, monkeypatch)
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
        runs.append((written, seen))
    assert runs[0] == runs[1]
    assert len(set(runs[0][0])) > 400  # the commands moved (clamped and rate limited, not stuck)


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
    source, target, short = np.zeros(2), np.zeros(2), np.zeros(1)
    read_only = np.zeros(2)
    read_only.flags.writeable = False
    everything = [*vectors, source, target, short, read_only]
    counts = [sys.getrefcount(v) for v in everything]
    failures = [
        (lambda: devio.Guard(*vectors[:5], np.zeros(2), [], False), "differ in length"),  # after all six held
        (lambda: devio.Guard(*vectors, [(source, target), (source, short)], False), "differ in length"),
        (lambda: devio.Guard(*vectors, [(source, target), (source, read_only)], False), "read-only|writable"),
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
