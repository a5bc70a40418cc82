"""rtloop's own CDR encoders give the bytes cyclonedds's serialiser gives, and the listener's timeline."""

from __future__ import annotations

import struct

import pytest

pytest.importorskip("cyclonedds")

from rtloop.ros.bridge import TickTimeline
from rtloop.ros.cdr import cycle_timing_cdr, encoder_for, float64_cdr, float64_multi_array_cdr, joint_state_cdr
from rtloop.ros.messages import Float64, float64_multi_array, joint_state

ODD_VALUES = [0.1 + 0.2, -0.0, 5e-324, float.fromhex("0x1.fffffffffffffp+1023"), float("nan")]


def padded(data: bytes) -> bytes:
    return data.ljust(-(-len(data) // 4) * 4, b"\0")  # DDS sends whole 4-byte words


@pytest.mark.parametrize("names", [(), ("pan",), ("pan", "tilt"), ("a", "bc", "déf", "ghij")])
def test_joint_state_bytes_match_cyclonedds(names: tuple[str, ...]) -> None:
    values = ODD_VALUES[: len(names)]
    stamp_ns = 1_700_000_000_987_654_321
    expected = padded(joint_state(names, values, stamp_ns).serialize())
    assert joint_state_cdr(names, values, stamp_ns) == expected


@pytest.mark.parametrize("label", ["", "u"])
@pytest.mark.parametrize("count", [0, 1, 5])
def test_float64_multi_array_bytes_match_cyclonedds(label: str, count: int) -> None:
    values = ODD_VALUES[:count]
    assert float64_multi_array_cdr(values, label) == padded(float64_multi_array(values, label).serialize())


def test_float64_bytes_match_cyclonedds() -> None:
    assert float64_cdr(-2.5) == padded(Float64(data=-2.5).serialize())


def test_encoder_for_each_bridged_type() -> None:
    encode = encoder_for("sensor_msgs/msg/JointState", ("pan", "tilt"))
    assert encode([1.0, 2.0], 5) == padded(joint_state(("pan", "tilt"), [1.0, 2.0], 5).serialize())
    assert encoder_for("std_msgs/msg/Float64")([3.0], 0) == padded(Float64(data=3.0).serialize())
    assert encoder_for("std_msgs/msg/Float64MultiArray")([1.0], 0) == padded(float64_multi_array([1.0]).serialize())


def test_cycle_timing_layout() -> None:
    data = cycle_timing_cdr(7, 1000, 1300, 1800)
    assert data[:4] == b"\x00\x01\x00\x00"
    assert struct.unpack("<Q5q", data[4:]) == (7, 1000, 1300, 1800, 300, 500)


def test_listener_timeline_learns_when_ticks_arrive() -> None:
    timeline = TickTimeline(t0_ns=1_000_000, period_ns=1_000_000, every=10)
    assert [timeline.next_tick(k) for k in (0, 9, 10, 25)] == [10, 10, 20, 30]
    assert timeline.look_at_ns(10) == 11_000_000  # no lag learnt yet: at the release
    timeline.found(10, found_ns=11_000_000 + 80_000, looked_again=True)
    assert timeline.lag_ns == 80_000 and timeline.look_at_ns(20) == 21_080_000
    timeline.found(20, found_ns=21_080_000, looked_again=False)  # there already: look earlier next time
    assert timeline.lag_ns == 70_000
    timeline.found(30, found_ns=10**12, looked_again=True)  # a stall: the lag never exceeds the interval
    assert timeline.lag_ns == 10_000_000
