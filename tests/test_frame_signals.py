"""Frame fields that carry signals: an encoder counter that wraps, unwrapped to a position in rad, and a
PWM duty with its range (io/bytelayout.py), as SPI and CAN frames declare them."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from conftest import layout_twins
from rtloop.io.bytelayout import ByteLayout, LayoutError, field_from_table

ENCODER = {"name": "pan_rad", "start_byte": 0, "type": "u16", "encoder": {"counts_per_rev": 1024, "gear_ratio": 4}}
DUTY = {"name": "pan_duty", "start_byte": 2, "type": "i16", "duty": {"full_scale": 1000, "range": [-0.9, 0.9]}}


def layout(*tables: dict) -> ByteLayout:
    return ByteLayout([field_from_table(t, f"receive[{i}]") for i, t in enumerate(tables)], 4, "receive")


def frame_with(count: int) -> bytearray:
    return bytearray(count.to_bytes(2, "little") + b"\0\0")


def test_a_wrapping_counter_reads_as_the_unwrapped_position() -> None:
    encoder = layout(ENCODER)
    per_count = 2 * math.pi / (1024 * 4)
    out = np.zeros(1)
    counts, readings = [65530, 65535, 3, 10, 65534, 100], []
    for count in counts:  # up through the wrap, back down through it, up again
        encoder.unpack_from(frame_with(count), 0, out)
        readings.append(out[0])
    totals = [65530, 65535, 65539, 65546, 65534, 65636]  # each change taken the short way round
    assert readings == pytest.approx([total * per_count for total in totals])


def test_a_position_packs_as_the_counter_would_show_it() -> None:
    """A twin's side: the position goes out as its count, wrapped; the reader unwraps it again."""
    sender, reader = layout(ENCODER), layout(ENCODER)
    per_count = 2 * math.pi / 4096
    frame, out = bytearray(4), np.zeros(1)
    for total in (65534, 65536 + 7, 65536 + 30000, 65536 + 60000, 2 * 65536 + 100):  # past the range, twice
        sender.pack_into(frame, 0, np.array([total * per_count]))
        assert int.from_bytes(frame[:2], "little") == total % 65536
        reader.unpack_from(frame, 0, out)
    assert out[0] == pytest.approx((2 * 65536 + 100) * per_count)


def test_a_layout_sent_to_the_task_process_starts_its_count_afresh() -> None:
    encoder = layout(ENCODER)
    encoder.unpack_from(frame_with(5), 0, np.zeros(1))
    copy = pickle.loads(pickle.dumps(encoder))
    out = np.zeros(1)
    copy.unpack_from(frame_with(65535), 0, out)
    assert out[0] == pytest.approx(65535 * 2 * math.pi / 4096)  # not -1 count from the 5 read before pickling


def test_a_duty_goes_out_scaled_and_clamped_to_its_range() -> None:
    duty = layout(DUTY)
    frame = bytearray(4)
    sent = []
    for value in (0.5, 1.5, -2.0, -0.25):
        duty.pack_into(frame, 0, np.array([value]))
        sent.append(int.from_bytes(frame[2:4], "little", signed=True))
    assert sent == [500, 900, -900, -250]  # never more than the declared 90 %
    out = np.zeros(1)
    duty.unpack_from(frame, 0, out)
    assert out[0] == -0.25
    with pytest.raises(ValueError, match=r"'pan_duty' is .*nan.*: a non-finite value is never sent"):
        duty.pack_into(frame, 0, np.array([math.nan]))


@pytest.mark.parametrize(("table", "words"), [
    ({**ENCODER, "type": "f32"}, "receive[0].encoder: an encoder counts: its type is an integer"),
    ({**ENCODER, "scale": 0.1}, "receive[0].scale: not with encoder"),
    ({**ENCODER, "encoder": {"counts_per_rev": 0}}, "receive[0].encoder.counts_per_rev: expected a number > 0"),
    ({**DUTY, "duty": {"full_scale": 1000, "range": [-2, 1]}}, "receive[0].duty.range: expected [min, max] within"),
    ({**DUTY, "type": "i8"}, "receive[0].duty: -0.9..0.9 × full_scale 1000 does not fit a i8"),
    ({**DUTY, "encoder": {"counts_per_rev": 10}}, "receive[0]: a field is an encoder or a duty, not both"),
])
def test_impossible_signal_fields_are_one_line(table: dict, words: str) -> None:
    with pytest.raises(LayoutError, match=None) as caught:
        field_from_table(table, "receive[0]")
    assert words in str(caught.value)


def test_an_spi_device_takes_them_and_runs_them_in_c_where_built() -> None:
    from rtloop.io.device import build_device

    device = build_device("spi", "fpga", {
        "device": "/dev/spidev0.0", "length": 8,
        "send": [{**DUTY, "start_byte": 1}],
        "receive": [{**ENCODER, "start_byte": 1}]}, "app.toml")
    assert device.input_names == ("pan_duty",) and device.output_names == ("pan_rad",)
    compiled = pytest.importorskip("rtloop.io._devio", reason="the devices' C part was not built (no compiler)")
    assert isinstance(device.tx_layout._compiled, compiled.Layout)
    assert isinstance(device.rx_layout._compiled, compiled.Layout)  # the SPI cycle stays one C call


def twins(tables: list[dict], size: int, monkeypatch: pytest.MonkeyPatch) -> tuple[ByteLayout, ByteLayout]:
    """The layout of ``tables`` twice: compiled, and the Python reference."""
    return layout_twins([field_from_table(t, f"frame[{i}]") for i, t in enumerate(tables)], size, monkeypatch)


@pytest.mark.parametrize("kind", ["u8", "i8", "u16", "i16", "u32", "i32"])
@pytest.mark.parametrize("order", ["little", "big"])
def test_encoders_and_duties_in_c_are_the_references_bit_for_bit(kind, order, monkeypatch) -> None:
    tables = [{"name": "enc", "start_byte": 0, "type": kind, "byte_order": order, "offset": 0.25,
               "encoder": {"counts_per_rev": 500, "gear_ratio": 3.7}},
              {"name": "duty", "start_byte": 4, "type": "i16", "byte_order": order,
               "duty": {"full_scale": 1000, "range": [-0.95, 0.95]}},
              {"name": "fduty", "start_byte": 6, "type": "f32", "duty": {"full_scale": 1.0, "range": [0.0, 0.5]}},
              {"name": "enc2", "start_byte": 10, "type": "i32", "encoder": {"counts_per_rev": 4096}}]
    compiled, reference = twins(tables, 16, monkeypatch)
    bits = 8 * int(kind[1:])
    per_count = 2 * math.pi / (500 * 3.7)
    rng = np.random.default_rng(11)
    position = np.zeros(4)
    # steps of up to a third of the counter's range, both ways: it wraps round many times
    steps = rng.uniform(-1, 1, (4_000, 4)) * [(2 ** bits / 3) * per_count, 0, 0, 5_000.0]
    for index, step in enumerate(steps):
        position += step
        position[1] = rng.uniform(-2, 2) if index % 7 else math.inf * rng.choice([-1, 1])
        position[2] = rng.uniform(-1, 1)
        frames = [bytearray(16), bytearray(16)]
        errors = []
        for one, frame in zip((compiled, reference), frames, strict=True):
            try:
                one.pack_into(frame, 0, memoryview(position))
                errors.append(None)
            except ValueError as error:
                errors.append(str(error))
        assert errors[0] == errors[1] and frames[0] == frames[1], (index, errors)
        outs = [np.zeros(4), np.zeros(4)]
        for one, out in zip((compiled, reference), outs, strict=True):
            one.unpack_from(frames[0], 0, out)
        assert outs[0].tobytes() == outs[1].tobytes(), (index, outs)
    assert abs(position[0]) > 2 ** bits * per_count or bits == 32  # it went round the counter


def test_a_reading_into_a_list_keeps_counting_where_the_c_layout_counts(monkeypatch) -> None:
    compiled, reference = twins([ENCODER], 4, monkeypatch)
    for count in (65_000, 100, 30_000, 65_000, 200):  # wraps up, then down
        seen = []
        for one in (compiled, reference):
            array_out, list_out = np.zeros(1), [0.0]
            one.unpack_from(frame_with(count), 0, array_out if count % 2 == 0 else list_out)
            seen.append(array_out[0] if count % 2 == 0 else list_out[0])
        assert seen[0] == seen[1], count


def test_a_float_duty_is_clamped_too() -> None:
    duty = layout({**DUTY, "start_byte": 0, "type": "f32", "duty": {"full_scale": 1.0, "range": [0.0, 0.5]}})
    frame, out = bytearray(8), np.zeros(1)
    duty.pack_into(frame, 0, np.array([0.75]))
    duty.unpack_from(frame, 0, out)
    assert out[0] == 0.5
