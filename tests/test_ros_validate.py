"""Validation of values arriving from ROS 2, rate-limited warnings, reject counters."""

from __future__ import annotations

import numpy as np
import pytest

from rtloop.errors import PortValueError
from rtloop.ipc.values import RejectedValues, validate_values
from rtloop.ros.validate import MessageValidator, RateLimitedWarner


def test_accepts_numbers_and_returns_a_float64_copy():
    source = np.array([1, 2, 3], dtype=np.int32)
    out = validate_values(source, 3)
    assert out.dtype == np.float64 and out.tolist() == [1.0, 2.0, 3.0]
    buffer = np.array([0.5, 0.25])
    out = validate_values(buffer, 2)
    buffer[0] = 9.0
    assert out[0] == 0.5


@pytest.mark.parametrize(
    ("values", "reason", "text"),
    [
        ([1.0, 2.0, 3.0], "length", "takes 2 values, got 3"),
        ([1.0], "length", "takes 2 values, got 1"),
        ([1.0, float("nan")], "nonfinite", "NaN or infinite value at index [1] of [1.0, nan]"),
        ([float("-inf"), 0.0], "nonfinite", "NaN or infinite value at index [0] of [-inf, 0.0]"),
        ([[1.0, 2.0]], "shape", "shape (1, 2)"),
        (["1", "2"], "type", "expected numbers"),
        ([1.0, None], "type", "expected numbers"),
        ([True, False], "type", "expected numbers"),
        ([1.0, [2.0]], "type", "expected numbers"),
    ],
)
def test_rejects_with_a_reason(values, reason, text):
    with pytest.raises(PortValueError) as info:
        validate_values(values, 2, where="/jiwy/setpoint")
    assert isinstance(info.value, RejectedValues) and isinstance(info.value, ValueError)
    assert info.value.reason == reason
    assert text in str(info.value) and "/jiwy/setpoint" in str(info.value)


def test_nonfinite_allowed_on_request():
    out = validate_values([float("nan"), float("inf")], 2, allow_nonfinite=True)
    assert np.isnan(out[0]) and np.isinf(out[1])


def test_rate_limited_warner_suppresses_and_reports_count():
    now = [0.0]
    emitted = []
    warner = RateLimitedWarner(1.0, emit=emitted.append, clock=lambda: now[0])
    assert warner.warn("bad", key="a")
    for _ in range(5):
        now[0] += 0.1
        assert not warner.warn("bad", key="a")
    assert warner.warn("other key", key="b")  # keys are limited separately
    assert warner.suppressed("a") == 5
    now[0] = 1.0
    assert warner.warn("bad", key="a")
    assert emitted == ["bad", "other key", "bad (5 similar warning(s) suppressed)"]
    assert warner.suppressed("a") == 0


def test_message_validator_counts_and_warns_once_per_interval():
    emitted = []
    validator = MessageValidator(2, what="/sp",
                                 warner=RateLimitedWarner(60.0, emit=emitted.append))
    assert validator.check([1.0, 2.0]).tolist() == [1.0, 2.0]
    for _ in range(3):
        assert validator.check([1.0]) is None
    assert validator.check([np.nan, 0.0]) is None
    counts = validator.counts
    assert counts.accepted == 1 and counts.total_rejected == 4
    assert counts.rejected["length"] == 3 and counts.rejected["nonfinite"] == 1
    assert len(emitted) == 2  # one per reason within the interval
    assert counts.to_json() == {
        "accepted": 1, "rejected": 4,
        "rejected_by_reason": {"type": 0, "shape": 0, "length": 3, "nonfinite": 1, "range": 0},
    }
