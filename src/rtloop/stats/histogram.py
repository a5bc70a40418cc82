"""A fixed-size log-linear histogram of signed int64 values (nanoseconds), HdrHistogram-style.

Why: a controller runs for days, so its statistics must not keep every sample. This
histogram decides its memory at creation and never allocates while recording more.

Layout (the HdrHistogram index math, for magnitudes m ≥ 0):

- ``significant_digits`` d gives ``sub_bucket_count = 2^ceil(log2(2·10^d))`` (256 for d=2);
  ``half = sub_bucket_count / 2``.
- Bucket 0 holds m < sub_bucket_count exactly (width 1). Bucket b ≥ 1 holds
  ``[half·2^b, sub_bucket_count·2^b)`` in ``half`` slots of width ``2^b``.
- Every magnitude of an int64 (up to 2^63) has a slot, so no value is ever out of range.

Sign: two rows of counters, one for values ≥ 0 and one for the magnitudes of values < 0
(period jitter is signed). An offset would make the error relative to the offset instead
of to the value; two rows keep it relative to |value| on both sides.

Error bound: a slot of width w starts at ≥ half·w, so every value is known to within
``w − 1 < |value| / half``: relative error < 1/half (1/128 ≈ 0.78 % for d=2). Values with
|value| < sub_bucket_count are exact. Percentiles report the highest value of the slot
(clamped to the exact max), so they never under-state a latency.

Exact: count, min, max and the sum (a Python int: an int64 sum of nanoseconds could
overflow, float128 is not portable and float64 would round), hence the mean. The standard
deviation is float64 (Chan's pairwise merge of batch moments), not exact but stable.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from rtloop.errors import RtloopError

DEFAULT_SIGNIFICANT_DIGITS = 2
_MAGNITUDE_BITS = 64  # magnitudes of int64 values go up to 2^63, which needs 64 bits
_POSITIVE, _NEGATIVE = 0, 1
_SUM_CHUNK = 1 << 30  # 2^30 values · 2^32 per low half < 2^63


class HistogramError(RtloopError, ValueError):
    """A histogram was asked something it cannot answer (bad value, percentile, layout)."""


class Histogram:
    """Counts of signed int64 values in log-linear slots; fixed memory, exact count/min/max/mean.

    Record with :meth:`record_many` (vectorised: give it whole batches) or :meth:`record`.
    """

    def __init__(self, significant_digits: int = DEFAULT_SIGNIFICANT_DIGITS) -> None:
        if significant_digits not in (1, 2, 3):
            raise HistogramError(f"significant_digits must be 1, 2 or 3, not {significant_digits!r}")
        self.significant_digits = significant_digits
        sub_bucket_count = 1 << math.ceil(math.log2(2 * 10**significant_digits))
        self._sub_bucket_bits = sub_bucket_count.bit_length() - 1
        self._half_bits = self._sub_bucket_bits - 1
        self._half = 1 << self._half_bits
        bucket_count = _MAGNITUDE_BITS - self._sub_bucket_bits + 1
        self.counts_per_sign = (bucket_count + 1) * self._half
        self._counts = np.zeros((2, self.counts_per_sign), dtype=np.int64)
        self.reset()

    # --- facts about the layout -------------------------------------------------------------
    @property
    def relative_error_bound(self) -> float:
        """Every recorded value is known to within this fraction of its magnitude (strictly less)."""
        return 1.0 / self._half

    @property
    def nbytes(self) -> int:
        """Bytes held by the counters; fixed at creation."""
        return int(self._counts.nbytes)

    def counters(self) -> npt.NDArray[np.int64]:
        """The counter array itself (read-only view): rows are values ≥ 0 and magnitudes of values < 0."""
        view = self._counts.view()
        view.flags.writeable = False
        return view

    # --- recording --------------------------------------------------------------------------
    def reset(self) -> None:
        self._counts[:] = 0
        self.count = 0  # values recorded
        self.sum = 0  # their exact sum (a Python int)
        self.min: int | None = None  # exact smallest value, None while empty
        self.max: int | None = None  # exact largest value, None while empty
        self._m2 = 0.0  # sum of squared deviations from the mean (float64, Chan's merge)

    def record(self, value: int) -> None:
        self.record_many([value])

    def record_many(self, values: npt.ArrayLike) -> None:
        """Record every value of a 1-D integer array (converted to int64) in one vectorised pass."""
        try:
            data = np.asarray(values)
        except OverflowError as error:
            raise HistogramError(f"histogram records int64 values: {error}") from None
        if data.size and data.dtype.kind not in "iu":
            raise HistogramError(f"histogram records int64 integers (nanoseconds), got an array of {data.dtype}")
        if data.size and data.dtype.kind == "u" and int(data.max()) > np.iinfo(np.int64).max:
            raise HistogramError(f"histogram records int64 values, got {int(data.max())}")
        data = data.astype(np.int64, copy=False).ravel()
        n = int(data.size)
        if n == 0:
            return
        negative = data < 0
        magnitude = data.view(np.uint64).copy()
        magnitude[negative] = ~magnitude[negative] + np.uint64(1)  # two's complement: |−2^63| = 2^63 fits
        index = self._index_of_magnitude(magnitude)
        index += negative.astype(np.int64) * self.counts_per_sign
        self._counts += np.bincount(index, minlength=2 * self.counts_per_sign).reshape(2, -1)
        self._add_moments(n, exact_sum(data), data)
        low, high = int(data.min()), int(data.max())
        self.min = low if self.min is None else min(self.min, low)
        self.max = high if self.max is None else max(self.max, high)

    def merge(self, other: Histogram) -> None:
        """Add ``other``'s counts into this one (same significant digits)."""
        if other.significant_digits != self.significant_digits:
            raise HistogramError(
                f"cannot merge a histogram of {other.significant_digits} significant digits "
                f"into one of {self.significant_digits}"
            )
        if other.count == 0:
            return
        self._counts += other._counts
        self._merge_moments(other.count, other.sum, other._m2)
        assert other.min is not None and other.max is not None
        self.min = other.min if self.min is None else min(self.min, other.min)
        self.max = other.max if self.max is None else max(self.max, other.max)

    # --- answers ----------------------------------------------------------------------------
    @property
    def mean(self) -> float:
        """Exact mean, correctly rounded to a float (NaN when empty)."""
        return self.sum / self.count if self.count else float("nan")

    @property
    def std(self) -> float:
        """Population standard deviation (NaN when empty)."""
        return math.sqrt(max(self._m2, 0.0) / self.count) if self.count else float("nan")

    def value_at_percentile(self, percentile: float) -> int:
        """The value at ``percentile`` (0–100), by HdrHistogram's (Java) rule.

        The target count is ``max(1, ceil(percentile/100 · count))`` (in float64, as Java and
        ``numpy.percentile(method="inverted_cdf")`` compute it); the answer is the highest value
        of the slot where the running count reaches it, clamped to the exact min and max
        (so percentile 0 is the min and 100 the max).
        """
        return self.values_at_percentiles([percentile])[0]

    def values_at_percentiles(self, percentiles: npt.ArrayLike) -> list[int]:
        wanted = np.asarray(percentiles, dtype=np.float64).ravel()
        if self.count == 0:
            raise HistogramError("no value recorded: an empty histogram has no percentiles")
        if not np.all((wanted >= 0.0) & (wanted <= 100.0)):
            raise HistogramError(f"percentiles must lie in [0, 100], got {wanted.tolist()}")
        # Values in ascending order: negative magnitudes from the largest down, then values ≥ 0.
        ascending = np.concatenate((self._counts[_NEGATIVE, ::-1], self._counts[_POSITIVE]))
        running = np.cumsum(ascending)
        targets = np.maximum(1, np.ceil(wanted / 100.0 * self.count)).astype(np.int64)
        positions = np.searchsorted(running, targets, side="left")
        assert self.min is not None and self.max is not None
        values = [min(max(self._highest_value_at(int(p)), self.min), self.max) for p in positions]
        # Java reports the slot's lowest value for p = 0; clamped, that is the exact min.
        return [self.min if w == 0.0 else v for w, v in zip(wanted.tolist(), values, strict=True)]

    # --- index math -------------------------------------------------------------------------
    def _index_of_magnitude(self, magnitude: npt.NDArray[np.uint64]) -> npt.NDArray[np.int64]:
        """Counter index of each magnitude (vectorised HdrHistogram ``countsArrayIndex``)."""
        bits = _bit_length(magnitude | np.uint64((1 << self._sub_bucket_bits) - 1))
        bucket = bits - self._sub_bucket_bits
        sub_bucket = (magnitude >> bucket.astype(np.uint64)).astype(np.int64)
        return (bucket << self._half_bits) + sub_bucket

    def _slot_of_index(self, index: int) -> tuple[int, int]:
        """(lowest magnitude, width) of the slot at a counter index of one sign."""
        bucket = (index >> self._half_bits) - 1
        sub_bucket = (index & (self._half - 1)) + self._half
        if bucket < 0:
            sub_bucket -= self._half
            bucket = 0
        return sub_bucket << bucket, 1 << bucket

    def _highest_value_at(self, position: int) -> int:
        """Highest signed value of the slot at ``position`` in the ascending order."""
        if position < self.counts_per_sign:  # a negative slot: its highest value is −(lowest magnitude)
            lowest, _ = self._slot_of_index(self.counts_per_sign - 1 - position)
            return -lowest
        lowest, width = self._slot_of_index(position - self.counts_per_sign)
        return lowest + width - 1

    def _add_moments(self, n: int, batch_sum: int, data: npt.NDArray[np.int64]) -> None:
        batch_mean = batch_sum / n
        deviation = data.astype(np.float64) - batch_mean
        self._merge_moments(n, batch_sum, float(np.dot(deviation, deviation)))

    def _merge_moments(self, n: int, batch_sum: int, batch_m2: float) -> None:
        if self.count:
            delta = batch_sum / n - self.sum / self.count
            self._m2 += batch_m2 + delta * delta * (self.count * n / (self.count + n))
        else:
            self._m2 = batch_m2
        self.count += n
        self.sum += batch_sum


def _bit_length(values: npt.NDArray[np.uint64]) -> npt.NDArray[np.int64]:
    """Bit length of each uint64 (vectorised ``int.bit_length``)."""
    # frexp on float64 is exact in the exponent except when rounding to 53 bits carries
    # into the next power of two (values just below 2^k, k > 53); one comparison fixes that.
    _, exponent = np.frexp(values.astype(np.float64))
    bits = exponent.astype(np.int64)
    too_long = (bits > 0) & ((values >> np.maximum(bits - 1, 0).astype(np.uint64)) == 0)
    bit_length: npt.NDArray[np.int64] = bits - too_long
    return bit_length


def exact_sum(data: npt.NDArray[np.int64]) -> int:
    """Sum of int64 values without overflow: split each into 32-bit halves summed separately."""
    total = 0
    for first in range(0, data.size, _SUM_CHUNK):  # each half-sum of a chunk fits int64
        chunk = data[first:first + _SUM_CHUNK]
        high = chunk >> 32  # arithmetic shift: in [−2^31, 2^31)
        low = chunk & 0xFFFF_FFFF  # in [0, 2^32)
        total += (int(high.sum()) << 32) + int(low.sum())
    return total
