"""Frames declared in an app file: byte layouts, CAN frames and ids, the SPI frame's counter and CRC.

Pure code: these run anywhere (the devices that carry the frames are tested in the guest)."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from io_guest_devices import KEPT_BYTES_ALLOWED, bytes_kept_by
from rtloop.io.bytelayout import ByteLayout, Field, LayoutError, field_from_table
from rtloop.io.canframes import (
    CAN_EFF_FLAG,
    DATA_AT,
    FD_MTU,
    HEADER,
    HeartbeatCounter,
    check_ids,
    frame_from_table,
    heartbeat_from_table,
)
from rtloop.io.spiframe import FrameCheck, crc16_ccitt, frame_layout, seal


def test_fields_pack_with_scale_offset_and_byte_order():
    layout = ByteLayout([Field("speed", 0, "i16", scale=0.01), Field("temp", 2, "u8", offset=-40.0),
                         Field("pos", 3, "i32", byte_order="big"), Field("gain", 7, "u8")], 8, "f")
    frame = bytearray(8)
    layout.pack_into(frame, 0, [-12.34, 25.0, 100000.0, 3.0])
    assert struct.unpack_from("<h", frame, 0)[0] == -1234
    assert frame[2] == 65
    assert struct.unpack_from(">i", frame, 3)[0] == 100000
    out = np.zeros(4)
    layout.unpack_from(frame, 0, out)
    assert out[0] == pytest.approx(-12.34) and out[1] == 25.0 and out[2] == 100000.0 and out[3] == 3.0


def test_pack_saturates_never_wraps_and_refuses_non_finite():
    layout = ByteLayout([Field("cmd", 0, "i16"), Field("duty", 2, "u8"), Field("f", 3, "f32")], 7, "f")
    frame = bytearray(7)
    layout.pack_into(frame, 0, [1e308, -5.0, 1.5])
    assert struct.unpack_from("<h", frame, 0)[0] == 32767 and frame[2] == 0
    layout.pack_into(frame, 0, [-1e308, 300.0, 1.5])
    assert struct.unpack_from("<h", frame, 0)[0] == -32768 and frame[2] == 255
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(ValueError, match=r"'cmd' is .*non-finite"):
            layout.pack_into(frame, 0, [bad, 0.0, 0.0])
        with pytest.raises(ValueError, match=r"'f' is .*non-finite"):
            layout.pack_into(frame, 0, [0.0, 0.0, bad])


def test_pack_rounds_to_nearest_and_round_trip_matches_the_wire():
    layout = ByteLayout([Field("a", 0, "i16", scale=0.5), Field("b", 2, "f32")], 6, "f")
    values, out = np.array([1.26, 0.1]), np.zeros(2)
    layout.round_trip(values, out)
    assert out[0] == 1.5  # 2.52 -> raw 3 -> 1.5
    assert out[1] == float(np.float32(0.1))


def test_layout_does_not_fit_or_overlaps_names_the_field():
    with pytest.raises(LayoutError, match=r"f\[1\] \('b'\): a i32 at byte 6 ends at byte 10, past the frame's 8 bytes"):
        ByteLayout([Field("a", 0, "u8"), Field("b", 6, "i32")], 8, "f")
    with pytest.raises(LayoutError, match="byte 1 is also used by 'a'"):
        ByteLayout([Field("a", 0, "i16"), Field("b", 1, "u8")], 8, "f")
    with pytest.raises(LayoutError, match="used twice"):
        ByteLayout([Field("a", 0, "u8"), Field("a", 1, "u8")], 8, "f")


@pytest.mark.parametrize(("table", "message"), [
    ({"name": "x", "start_byte": 0, "type": "i12"}, "type: expected one of"),
    ({"name": "x", "start_byte": -1}, "start_byte: expected an integer >= 0"),
    ({"name": "x", "start_byte": 0, "scale": 0}, "scale: must not be 0"),
    ({"name": "x", "start_byte": 0, "scale": math.nan}, "scale: expected a finite number"),
    ({"name": "x", "start_byte": 0, "offset": 1e999}, "offset: expected a finite number"),
    ({"name": "x", "start_byte": 0, "byte_order": "middle"}, "byte_order: expected"),
    ({"name": "", "start_byte": 0}, "name: expected a non-empty string"),
    ({"name": "x", "start_byte": 0, "sclae": 2}, "unknown key 'sclae'"),
])
def test_field_table_errors_are_one_line_naming_the_key(table, message):
    with pytest.raises(LayoutError, match=message) as error:
        field_from_table(table, "devices.d.send[0].signals[0]")
    assert str(error.value).startswith("devices.d.send[0].signals[0]") and "\n" not in str(error.value)


def _sent(table, fd_bus=False):
    return frame_from_table(table, "devices.drive.send[0]", fd_bus=fd_bus, receive=False)


def test_classic_frame_bytes_are_a_socketcan_can_frame():
    frame = _sent({"id": 0x123, "signals": [{"name": "cmd", "start_byte": 0, "type": "i16"}]})
    assert (frame.mtu, frame.length_bytes, frame.fd) == (16, 8, False)
    buffer = frame.new_buffer()
    frame.layout.pack_into(buffer, DATA_AT, [-2.0])
    assert HEADER.unpack_from(buffer, 0) == (0x123, 8, 0)
    assert bytes(buffer[DATA_AT:DATA_AT + 2]) == struct.pack("<h", -2)


def test_fd_frame_and_extended_id():
    frame = _sent({"id": 0x1ABCDEF0, "extended": True, "length": 64,
                   "signals": [{"name": f"s{i}", "start_byte": 8 * i, "type": "f64"} for i in range(8)]}, fd_bus=True)
    assert frame.mtu == FD_MTU and frame.wire_id == 0x1ABCDEF0 | CAN_EFF_FLAG
    assert HEADER.unpack_from(frame.new_buffer(), 0)[:2] == (0x1ABCDEF0 | CAN_EFF_FLAG, 64)


@pytest.mark.parametrize(("table", "fd_bus", "message"), [
    ({"id": 0x800}, False, r"outside the 11-bit range 0..0x7FF \(set extended = true"),
    ({"id": 0x20000000, "extended": True}, False, "outside the 29-bit range"),
    ({"id": 1, "length": 9}, False, "classic CAN frame carries 0 to 8 bytes, not 9 .declare the bus fd = true"),
    ({"id": 1, "length": 10}, True, "not 10 .the next one is 12"),
    ({"id": 1, "fd": True}, False, "a CAN FD frame on a bus not declared fd = true"),
    ({"id": 1, "signals": [{"name": "a", "start_byte": 6, "type": "i32"}]}, False,
     r"does not fit the frame"),
    ({"id": 1, "length": 2, "signals": [{"name": "a", "start_byte": 1, "type": "i16"}]}, False,
     r"ends at byte 3, past the frame's 2 bytes"),
    ({"id": "0x10"}, False, "id: expected an integer"),
    ({"id": 1, "timeout_ms": 5}, False, "unknown key 'timeout_ms'"),
])
def test_bad_frames_are_refused_with_one_line(table, fd_bus, message):
    with pytest.raises(LayoutError, match=message) as error:
        _sent(table, fd_bus)
    assert str(error.value).startswith("devices.drive.send[0]") and "\n" not in str(error.value)


def test_received_frames_need_a_timeout_and_say_what_missing_means():
    table = {"id": 0x181, "signals": [{"name": "pos", "start_byte": 0, "type": "i32"}]}
    with pytest.raises(LayoutError, match="timeout_ms: expected a positive number"):
        frame_from_table(table, "r", fd_bus=False, receive=True)
    with pytest.raises(LayoutError, match="on_missing: expected 'fault' or 'stale'"):
        frame_from_table({**table, "timeout_ms": 5, "on_missing": "ignore"}, "r", fd_bus=False, receive=True)
    frame = frame_from_table({**table, "timeout_ms": 2.5, "on_missing": "stale"}, "r", fd_bus=False, receive=True)
    assert (frame.timeout_ns, frame.on_missing) == (2_500_000, "stale")


def test_frame_id_clash_names_both_frames():
    a = _sent({"id": 0x100})
    b = frame_from_table({"id": 0x100, "timeout_ms": 1}, "devices.drive.receive[0]", fd_bus=False, receive=True)
    with pytest.raises(LayoutError, match=r"devices.drive.receive\[0\].id: frame id clash: 0x100 is also the id of "
                                          r"devices.drive.send\[0\]"):
        check_ids([a, b])
    beat = heartbeat_from_table({"id": 0x100}, "devices.drive.heartbeat")
    with pytest.raises(LayoutError, match=r"heartbeat\.id: frame id clash"):
        check_ids([a], beat)
    # the same number as an 11-bit and a 29-bit id are two different frames
    check_ids([a, _sent({"id": 0x100, "extended": True})])


def test_heartbeat_counts_every_cycle_and_wraps():
    beat = HeartbeatCounter(heartbeat_from_table({"id": 0x700}, "hb"))
    seen = [beat.next()[DATA_AT] for _ in range(258)]
    assert seen[:3] == [0, 1, 2] and seen[255:] == [255, 0, 1]


def test_crc16_ccitt_false_check_value():
    assert crc16_ccitt(b"123456789") == 0x29B1


def test_spi_frame_reserves_counter_and_crc_bytes():
    with pytest.raises(LayoutError, match=r"send\[0\] \('a'\): byte 0 is also used by the sequence counter"):
        frame_layout([Field("a", 0, "u8")], 8, "devices.fpga.send")
    with pytest.raises(LayoutError, match=r"byte 6 is also used by the CRC \(bytes 6 and 7\)"):
        frame_layout([Field("a", 5, "i16")], 8, "devices.fpga.send")
    with pytest.raises(LayoutError, match="no room for the counter and the CRC"):
        frame_layout([], 2, "devices.fpga.send")
    assert frame_layout([Field("a", 1, "i16")], 8, "x").names == ["a"]


def test_spi_layout_errors_name_the_index_in_the_app_file_and_the_length_needed():
    """The counter and CRC are not counted among the file's fields: receive[0] is the file's first."""
    fields = [Field("speed", 1, "f32"), Field("cur", 5, "f32")]
    with pytest.raises(LayoutError) as short:
        frame_layout(fields, 6, "receive")
    assert str(short.value) == ("receive[0] ('speed'): byte 4 is also used by the CRC (bytes 4 and 5); the frame's 6 "
                                "bytes hold the counter, the signals and the CRC from length 11")
    with pytest.raises(LayoutError, match=r"^receive\[1\] \('cur'\): a f32 at byte 5 ends at byte 9, past"):
        frame_layout([Field("speed", 1, "f32"), Field("cur", 5, "f32")], 8, "receive")
    with pytest.raises(LayoutError, match=r"^send\[1\] \('b'\): byte 0 is also used by the sequence counter "
                                          r"\(byte 0\); signals start at byte 1$"):
        frame_layout([Field("a", 1, "u8"), Field("b", 0, "u8")], 8, "send")
    assert frame_layout(fields, 11, "receive").names == ["speed", "cur"]


def test_spi_frame_check_counter_and_crc():
    frame = bytearray(6)
    view = memoryview(frame)[:4]
    echo = FrameCheck(6, "echo")
    for counter in (0, 1, 255):
        frame[1:4] = bytes([counter, 2, 3])
        seal(frame, view, counter)
        echo.sent(counter)
        assert echo.accept(frame, view)
    frame[2] ^= 0x10  # one bit flipped on the wire
    assert not echo.accept(frame, view) and echo.bad_crc == 1 and echo.last_error == "bad CRC"
    seal(frame, view, 7)
    echo.sent(8)
    assert not echo.accept(frame, view) and echo.bad_counter == 1 and "counter 7 where 8" in echo.last_error

    previous = FrameCheck(6, "previous")
    previous.sent(0)
    seal(frame, view, 200)  # first answer: nothing to compare with
    assert previous.accept(frame, view)
    previous.after(0)
    previous.sent(1)
    seal(frame, view, 0)
    assert previous.accept(frame, view)
    previous.after(1)
    seal(frame, view, 0)  # the device did not see the frame before
    assert not previous.accept(frame, view)


def test_packing_allocates_nothing_that_stays():
    frame = _sent({"id": 1, "signals": [{"name": "a", "start_byte": 0, "type": "i16", "scale": 0.01},
                                        {"name": "b", "start_byte": 2, "type": "f32"}]})
    buffer, values, out = frame.new_buffer(), np.array([1.5, -2.0]), np.zeros(2)
    view = memoryview(frame.new_buffer())[:14]

    def cycle():
        frame.layout.pack_into(buffer, DATA_AT, values)
        frame.layout.unpack_from(buffer, DATA_AT, out)
        seal(buffer, view, 3)

    assert bytes_kept_by(cycle, 10_000) <= KEPT_BYTES_ALLOWED
    assert list(out) == [1.5, -2.0]
