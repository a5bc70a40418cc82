"""Timing statistics of one task, fed batch by batch, in memory that does not grow with the run.

:func:`rtloop.stats.timing.task_timing` needs every sample of a run; a controller that runs for
days cannot keep them. :class:`StreamingTaskTiming` takes the same (cycle, release, start,
end) records in cycle order, as the supervisor drains them, and gives the same
:class:`~rtloop.stats.timing.TaskTiming` at any moment:

- exactly the same: cycles, trimmed, deadline misses, overruns, jitter over 3 %, and each
  distribution's min, max and mean (the mean exact here; ``task_timing``'s float64 mean
  agrees to ~1e-15);
- within the histogram's bound (< 1/128 ≈ 0.78 % of |value|): the percentiles, which follow
  HdrHistogram's rule — the value at rank ``ceil(p/100·n)`` — where ``task_timing``
  interpolates linearly between the two neighbouring ranks;
- to float rounding: the standard deviations and the drift (streamed co-moments).

One engine: every value here is computed by :mod:`~rtloop.stats.timing`'s own functions
(wake-up latency, execution time, period and cycle-to-cycle jitter, misses, late starts) on
each batch, the same functions ``task_timing`` and the report use; only how a distribution
is summarised differs (a histogram here, every sample there).

Trimming as ``task_timing``: the first ``trim`` cycles are dropped as they arrive; the last
``trim`` are held back in a small fixed buffer and enter the distributions only when newer
cycles push them out, so at any moment the statistics leave out the newest ``trim`` cycles.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from rtloop.errors import RtloopError

from .histogram import DEFAULT_SIGNIFICANT_DIGITS, Histogram, exact_sum
from .timing import (
    DEFAULT_TRIM,
    DRIFT_WINDOW_CYCLES,
    THESIS_JITTER_FRACTION,
    Distribution,
    TaskTiming,
    TimingSamples,
    cycle_to_cycle_jitter_ns,
    deadline_misses,
    execution_ns,
    jitter_over_fraction,
    late_starts,
    period_jitter_ns,
    wakeup_latency_ns,
)

_PERCENTILES = (50.0, 99.0, 99.9)


class TimingOrderError(RtloopError, ValueError):
    """Timing records arrived out of cycle order (each batch must follow the previous one)."""


class StreamingTaskTiming:
    """Streaming counterpart of :func:`rtloop.stats.timing.task_timing` for one task."""

    def __init__(
        self,
        period_ns: int,
        *,
        trim: int = DEFAULT_TRIM,
        overrun_policy: str = "skip",
        significant_digits: int = DEFAULT_SIGNIFICANT_DIGITS,
    ) -> None:
        if period_ns <= 0:
            raise ValueError(f"period_ns must be positive, got {period_ns}")
        if trim < 0:
            raise ValueError(f"trim must be ≥ 0, got {trim}")
        self.period_ns = int(period_ns)
        self.trim = int(trim)
        self.overrun_policy = overrun_policy
        # Every cycle.
        self.cycles = 0
        self._first_cycle: int | None = None
        self._last_cycle: int | None = None
        self._deadline_misses = 0
        self._late_starts = 0
        # Trimming: the head is counted away, the tail waits in a fixed buffer.
        self._head_skipped = 0
        self._held = np.empty((self.trim, 4), dtype=np.int64)
        self._held_count = 0
        # The trimmed core.
        self.latency = Histogram(significant_digits)
        self.period_jitter = Histogram(significant_digits)
        self.cycle_jitter = Histogram(significant_digits)
        self.execution = Histogram(significant_digits)
        self._jitter_over_3pct = 0
        self._last_core = np.empty((0, 4), dtype=np.int64)  # the newest two core rows: periods span batches
        self._drift = _CoMoments()

    # --- feeding ----------------------------------------------------------------------------
    def add(self, records: npt.ArrayLike) -> None:
        """Add an n × 4 array of (cycle, release_ns, start_ns, end_ns) rows, in cycle order."""
        rows = np.asarray(records, dtype=np.int64).reshape(-1, 4)
        self.add_columns(rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3])

    def add_columns(
        self,
        cycle: npt.ArrayLike,
        release_ns: npt.ArrayLike,
        start_ns: npt.ArrayLike,
        end_ns: npt.ArrayLike,
    ) -> None:
        """Add one batch given as four equally long arrays, in cycle order."""
        columns = [np.asarray(a, dtype=np.int64).ravel() for a in (cycle, release_ns, start_ns, end_ns)]
        n = columns[0].size
        if any(c.size != n for c in columns):
            raise ValueError(f"timing columns differ in length: {[c.size for c in columns]}")
        if n == 0:
            return
        self._check_order(columns[0])
        self._count_every_cycle(*columns)
        rows = np.stack(columns, axis=1)
        skip = min(self.trim - self._head_skipped, n)
        self._head_skipped += skip
        self._push_through_tail(rows[skip:])

    def _check_order(self, cycle: npt.NDArray[np.int64]) -> None:
        steps = np.diff(cycle)
        if steps.size and steps.min() <= 0:
            at = int(np.argmax(steps <= 0))
            raise TimingOrderError(f"timing records out of cycle order: cycle {cycle[at + 1]} after {cycle[at]}")
        if self._last_cycle is not None and cycle[0] <= self._last_cycle:
            raise TimingOrderError(
                f"timing records out of cycle order: batch starts at cycle {cycle[0]}, "
                f"after cycle {self._last_cycle}"
            )

    def _count_every_cycle(self, cycle: npt.NDArray[np.int64], release: npt.NDArray[np.int64],
                           start: npt.NDArray[np.int64], end: npt.NDArray[np.int64]) -> None:
        """What task_timing counts over every cycle, trimmed or not (with its own functions)."""
        if self._first_cycle is None:
            self._first_cycle = int(cycle[0])
        self._last_cycle = int(cycle[-1])
        self.cycles += int(cycle.size)
        batch = TimingSamples(cycle, release, start, end)
        self._deadline_misses += deadline_misses(batch, self.period_ns)
        self._late_starts += late_starts(batch, self.period_ns)

    def _push_through_tail(self, rows: npt.NDArray[np.int64]) -> None:
        """Hold back the newest ``trim`` rows; the rows they push out join the statistics."""
        if self.trim == 0:
            self._add_core(rows)
            return
        if rows.shape[0] == 0:
            return
        waiting = np.concatenate((self._held[: self._held_count], rows))
        released = waiting[: -self.trim]
        kept = waiting[-self.trim:]
        self._held[: kept.shape[0]] = kept
        self._held_count = kept.shape[0]
        if released.shape[0]:
            self._add_core(released)

    def _add_core(self, rows: npt.NDArray[np.int64]) -> None:
        """Feed rows of the trimmed core, in order, to the distributions.

        The values are task_timing's own functions of the samples. A period spans two rows
        and a change of period three, so the newest two core rows of the previous batch go
        in front: each pair and triple is counted once, in the batch of its last row.
        """
        batch = TimingSamples(*(rows[:, i] for i in range(4)))
        joined = np.concatenate((self._last_core, rows))
        with_previous = TimingSamples(*(joined[-(rows.shape[0] + 1):, i] for i in range(4)))
        with_two_previous = TimingSamples(*(joined[:, i] for i in range(4)))
        latency = wakeup_latency_ns(batch)
        self.latency.record_many(latency)
        self.execution.record_many(execution_ns(batch))
        self._drift.add(batch.cycle, latency)
        self.period_jitter.record_many(period_jitter_ns(with_previous, self.period_ns))
        self._jitter_over_3pct += jitter_over_fraction(with_previous, self.period_ns, THESIS_JITTER_FRACTION)
        self.cycle_jitter.record_many(cycle_to_cycle_jitter_ns(with_two_previous))
        self._last_core = joined[-2:].copy()

    # --- answers ----------------------------------------------------------------------------
    @property
    def overruns(self) -> int:
        if self.overrun_policy == "skip":
            if self._first_cycle is None or self._last_cycle is None:
                return 0
            return (self._last_cycle - self._first_cycle) - (self.cycles - 1)
        return self._late_starts

    def task_timing(self) -> TaskTiming:
        """The statistics so far, in the record ``task_timing`` returns (call it as often as wanted)."""
        return TaskTiming(
            period_ns=self.period_ns,
            cycles=self.cycles,
            trimmed=2 * self.trim if self.cycles > 2 * self.trim else self.cycles,
            latency_ns=distribution_of(self.latency),
            period_jitter_ns=distribution_of(self.period_jitter),
            cycle_jitter_ns=distribution_of(self.cycle_jitter),
            exec_ns=distribution_of(self.execution),
            drift_ns_per_10k_cycles=round(self._drift.slope() * DRIFT_WINDOW_CYCLES, 1),
            deadline_misses=self._deadline_misses,
            overruns=self.overruns,
            jitter_over_3pct=self._jitter_over_3pct,
        )

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays held (fixed at creation)."""
        histograms = (self.latency, self.period_jitter, self.cycle_jitter, self.execution)
        return sum(h.nbytes for h in histograms) + int(self._held.nbytes)


def distribution_of(histogram: Histogram) -> Distribution:
    """A :class:`~rtloop.stats.timing.Distribution` from a histogram (all NaN when it is empty)."""
    if histogram.count == 0:
        return Distribution.of([])
    assert histogram.min is not None and histogram.max is not None
    p50, p99, p999 = histogram.values_at_percentiles(_PERCENTILES)
    return Distribution(
        min=float(histogram.min),
        mean=histogram.mean,
        p50=float(p50),
        p99=float(p99),
        p999=float(p999),
        max=float(histogram.max),
        std=histogram.std,
    )


class _CoMoments:
    """Least-squares slope of y against x, streamed (Chan et al.'s pairwise update of co-moments)."""

    def __init__(self) -> None:
        self.n = 0
        self.sum_x = 0  # exact (Python ints), so the means are exact
        self.sum_y = 0
        self.c_xx = 0.0  # Σ (x − x̄)²
        self.c_xy = 0.0  # Σ (x − x̄)(y − ȳ)

    def add(self, x: npt.NDArray[np.int64], y: npt.NDArray[np.int64]) -> None:
        n = int(x.size)
        if n == 0:
            return
        sum_x, sum_y = exact_sum(x), exact_sum(y)
        dx = x.astype(np.float64) - sum_x / n
        dy = y.astype(np.float64) - sum_y / n
        c_xx, c_xy = float(np.dot(dx, dx)), float(np.dot(dx, dy))
        if self.n:
            weight = self.n * n / (self.n + n)
            delta_x = sum_x / n - self.sum_x / self.n
            delta_y = sum_y / n - self.sum_y / self.n
            c_xx += delta_x * delta_x * weight
            c_xy += delta_x * delta_y * weight
        self.c_xx += c_xx
        self.c_xy += c_xy
        self.n += n
        self.sum_x += sum_x
        self.sum_y += sum_y

    def slope(self) -> float:
        """0 with fewer than two points or no spread in x, as ``drift_ns_per_window``."""
        if self.n < 2 or self.c_xx == 0.0:
            return 0.0
        return self.c_xy / self.c_xx
