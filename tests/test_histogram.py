"""The fixed-size log-linear histogram: exact moments, bounded percentile error, fixed memory."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from rtloop.stats.histogram import Histogram, HistogramError, _bit_length

INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1


def int64_arrays(low: int = INT64_MIN, high: int = INT64_MAX, max_size: int = 400) -> st.SearchStrategy:
    return hnp.arrays(np.int64, st.integers(1, max_size), elements=st.integers(low, high))


# Data shaped like timings (a few magnitudes, both signs) as well as anything an int64 holds.
value_arrays = st.one_of(
    int64_arrays(),
    int64_arrays(-2_000_000, 2_000_000),
    int64_arrays(0, 300),
    int64_arrays(-(10**12), 10**12),
)
percentiles = st.one_of(st.sampled_from([0.0, 50.0, 99.0, 99.9, 100.0]), st.floats(0.0, 100.0))


@settings(max_examples=300, deadline=None)
@given(values=value_arrays, percentile=percentiles)
def test_percentile_is_within_the_stated_bound_of_numpy(values: np.ndarray, percentile: float) -> None:
    histogram = Histogram()
    histogram.record_many(values)
    # numpy's "inverted_cdf" is HdrHistogram's rule: the value at rank ceil(p/100·n).
    exact = int(np.percentile(values, percentile, method="inverted_cdf"))
    got = histogram.value_at_percentile(percentile)
    assert exact <= got  # the slot's highest value: never under-states
    assert got - exact <= histogram.relative_error_bound * abs(exact)
    assert histogram.relative_error_bound <= 0.01


@settings(max_examples=200, deadline=None)
@given(values=value_arrays)
@example(values=np.array([-(2**63)], dtype=np.int64))  # np.abs(-2**63) overflows to itself: negative
def test_count_min_max_sum_and_mean_are_exact(values: np.ndarray) -> None:
    histogram = Histogram()
    histogram.record_many(values)
    python_ints = [int(v) for v in values]
    assert histogram.count == len(python_ints)
    assert histogram.min == min(python_ints) and histogram.max == max(python_ints)
    assert histogram.sum == sum(python_ints)  # would overflow an int64 sum for large values
    assert histogram.mean == float(Fraction(sum(python_ints), len(python_ints)))
    # float64 moments: the std is exact to rounding at the values' magnitude (1e14 ns: ~0.02)
    magnitude = float(max((abs(v) for v in python_ints), default=0))  # Python ints: abs(-2**63) fits
    assert math.isclose(histogram.std, float(np.std(values.astype(np.float64))), rel_tol=1e-9,
                        abs_tol=1e-6 + 1e-15 * magnitude * max(1, len(values)))


@settings(max_examples=100, deadline=None)
@given(values=int64_arrays(-(10**12), 10**12), cuts=st.lists(st.integers(0, 400), max_size=6))
def test_batches_and_merges_give_the_same_histogram_as_one_pass(values: np.ndarray, cuts: list[int]) -> None:
    whole = Histogram()
    whole.record_many(values)
    batched, merged = Histogram(), Histogram()
    for part in np.split(values, sorted(c for c in cuts if c <= values.size)):
        batched.record_many(part)
        piece = Histogram()
        piece.record_many(part)
        merged.merge(piece)
    for other in (batched, merged):
        assert np.array_equal(other.counters(), whole.counters())
        assert (other.count, other.sum, other.min, other.max) == (whole.count, whole.sum, whole.min, whole.max)
        assert math.isclose(other.std, whole.std, rel_tol=1e-9, abs_tol=1e-6)
        assert other.values_at_percentiles([1, 50, 99.9]) == whole.values_at_percentiles([1, 50, 99.9])


def test_small_magnitudes_are_exact_on_both_sides() -> None:
    values = np.arange(-255, 256, dtype=np.int64)
    histogram = Histogram()
    histogram.record_many(values)
    for p in (0.1, 10, 25, 50, 75, 99):
        assert histogram.value_at_percentile(p) == int(np.percentile(values, p, method="inverted_cdf"))


def test_the_whole_int64_range_is_recorded_without_overflow() -> None:
    values = np.array([INT64_MIN, INT64_MIN + 1, -1, 0, 1, INT64_MAX - 1, INT64_MAX], dtype=np.int64)
    histogram = Histogram()
    histogram.record_many(values)
    assert (histogram.min, histogram.max) == (INT64_MIN, INT64_MAX)
    assert histogram.sum == sum(int(v) for v in values) == -2
    assert histogram.value_at_percentile(0) == INT64_MIN
    assert histogram.value_at_percentile(100) == INT64_MAX
    assert histogram.value_at_percentile(50) == 0  # rank ceil(3.5) = 4 of 7


@given(st.integers(54, 64), st.integers(-3, 3))
def test_bit_length_is_exact_where_float64_rounds(power: int, offset: int) -> None:
    value = min(max((1 << power) + offset, 0), 2**64 - 1)
    got = _bit_length(np.array([value], dtype=np.uint64))
    assert int(got[0]) == value.bit_length()


def test_memory_is_fixed_while_ten_million_values_are_recorded() -> None:
    histogram = Histogram()
    counters = histogram.counters()
    size_before, bytes_before, address_before = counters.size, histogram.nbytes, counters.ctypes.data
    rng = np.random.default_rng(7)
    for _ in range(100):
        histogram.record_many(rng.integers(-(10**9), 10**9, size=100_000))
    after = histogram.counters()
    assert histogram.count == 10_000_000
    assert (after.size, histogram.nbytes, after.ctypes.data) == (size_before, bytes_before, address_before)
    assert int(after.sum()) == 10_000_000


@pytest.mark.parametrize(("digits", "bound", "counters_per_sign"), [(1, 1 / 16, 976), (2, 1 / 128, 7424),
                                                                     (3, 1 / 1024, 56320)])
def test_layout_follows_significant_digits(digits: int, bound: float, counters_per_sign: int) -> None:
    histogram = Histogram(digits)
    assert histogram.relative_error_bound == bound
    assert histogram.counts_per_sign == counters_per_sign
    assert histogram.nbytes == 2 * counters_per_sign * 8


def test_bad_requests_raise_one_clear_error() -> None:
    histogram = Histogram()
    with pytest.raises(HistogramError, match="empty histogram"):
        histogram.value_at_percentile(50)
    with pytest.raises(HistogramError, match="int64 integers"):
        histogram.record_many(np.array([1.5]))
    with pytest.raises(HistogramError, match="int64"):
        histogram.record_many(np.array([2**63], dtype=np.uint64))
    with pytest.raises(HistogramError, match="int64"):
        histogram.record(2**70)
    histogram.record(5)
    with pytest.raises(HistogramError, match=r"\[0, 100\]"):
        histogram.value_at_percentile(101)
    with pytest.raises(HistogramError, match="significant digits"):
        histogram.merge(Histogram(3))
    with pytest.raises(HistogramError, match="significant_digits"):
        Histogram(5)


def test_reset_empties_but_keeps_the_counters() -> None:
    histogram = Histogram()
    address = histogram.counters().ctypes.data
    histogram.record_many(np.array([3, -4, 10**9]))
    histogram.reset()
    assert histogram.count == 0 and histogram.min is None and int(histogram.counters().sum()) == 0
    assert math.isnan(histogram.mean)
    assert histogram.counters().ctypes.data == address
