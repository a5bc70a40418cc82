"""Timing samples → statistics (pure functions, no I/O).

A task records, for every cycle k, its release time (T0 + k·P), the time it woke up
(start) and the time its step finished (end). From those:

- wake-up latency = start − release (what cyclictest reports);
- period jitter = (start_k − start_{k−1}) − P between consecutive cycles;
- cycle-to-cycle jitter = difference of consecutive actual periods;
- execution time = end − start;
- drift = how far the start times walk away from the ideal timeline, per 10,000 cycles
  (≈0 with absolute-time sleeping; a relative sleep drifts by its overhead every cycle);
- deadline miss = a cycle that finished after its deadline (release + P);
- the thesis's criterion: cycles whose period deviates from P by more than 3 %.

Distributions trim the first and last ``trim`` cycles (20 by default, as the thesis
does); counts of misses and overruns use every cycle.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import numpy.typing as npt

from rtloop.stats import DEFAULT_TRIM as DEFAULT_TRIM

DRIFT_WINDOW_CYCLES = 10_000
THESIS_JITTER_FRACTION = 0.03

IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class Distribution:
    """Summary of a set of durations in nanoseconds."""

    min: float
    """Smallest value."""
    mean: float
    """Arithmetic mean."""
    p50: float
    """Median."""
    p99: float
    """99th percentile."""
    p999: float
    """99.9th percentile."""
    max: float
    """Largest value."""
    std: float
    """Standard deviation."""

    @staticmethod
    def of(values: npt.ArrayLike) -> Distribution:
        data = np.asarray(values, dtype=np.float64)
        if data.size == 0:
            nan = float("nan")
            return Distribution(nan, nan, nan, nan, nan, nan, nan)
        p50, p99, p999 = np.percentile(data, [50, 99, 99.9])
        return Distribution(
            min=float(data.min()),
            mean=float(data.mean()),
            p50=float(p50),
            p99=float(p99),
            p999=float(p999),
            max=float(data.max()),
            std=float(data.std()),
        )

    def to_json(self) -> dict[str, float | None]:
        return {k: (None if np.isnan(v) else round(v, 1)) for k, v in asdict(self).items()}


@dataclass(frozen=True, slots=True)
class TimingSamples:
    """Per-cycle timing of one task, as recorded (all CLOCK_MONOTONIC nanoseconds)."""

    cycle: IntArray
    release_ns: IntArray
    start_ns: IntArray
    end_ns: IntArray

    @staticmethod
    def from_records(records: npt.NDArray[np.int64]) -> TimingSamples:
        """From an n × 4 array of (cycle, release, start, end) rows, in cycle order."""
        records = np.asarray(records, dtype=np.int64).reshape(-1, 4)
        order = np.argsort(records[:, 0], kind="stable")
        records = records[order]
        return TimingSamples(*(records[:, i].copy() for i in range(4)))

    def __len__(self) -> int:
        return int(self.cycle.size)

    def trimmed(self, trim: int) -> TimingSamples:
        if trim <= 0 or len(self) <= 2 * trim:
            return self if trim <= 0 else TimingSamples(*(a[:0] for a in self._arrays()))
        return TimingSamples(*(a[trim:-trim] for a in self._arrays()))

    def _arrays(self) -> tuple[IntArray, IntArray, IntArray, IntArray]:
        return self.cycle, self.release_ns, self.start_ns, self.end_ns


def wakeup_latency_ns(samples: TimingSamples) -> IntArray:
    return samples.start_ns - samples.release_ns


def execution_ns(samples: TimingSamples) -> IntArray:
    return samples.end_ns - samples.start_ns


def consecutive(samples: TimingSamples) -> npt.NDArray[np.bool_]:
    """Mask over pairs (k−1, k): True where cycle k directly follows cycle k−1."""
    follows: npt.NDArray[np.bool_] = np.diff(samples.cycle) == 1
    return follows


def period_jitter_ns(samples: TimingSamples, period_ns: int) -> IntArray:
    """(start_k − start_{k−1}) − P for consecutive cycles (skipped releases excluded)."""
    periods = np.diff(samples.start_ns)
    return (periods - period_ns)[consecutive(samples)]


def cycle_to_cycle_jitter_ns(samples: TimingSamples) -> IntArray:
    """Actual period k minus actual period k−1, for three consecutive cycles."""
    ok = consecutive(samples)
    periods = np.diff(samples.start_ns)
    both = ok[1:] & ok[:-1]
    return np.diff(periods)[both]


def drift_ns_per_window(samples: TimingSamples, window_cycles: int = DRIFT_WINDOW_CYCLES) -> float:
    """Least-squares slope of the wake-up latency against the cycle number, × window.

    Absolute-time sleeping keeps this near 0; accumulating relative sleeps walk away
    from the ideal timeline and show a positive drift.
    """
    if len(samples) < 2:
        return 0.0
    cycles = samples.cycle.astype(np.float64)
    latency = wakeup_latency_ns(samples).astype(np.float64)
    centered = cycles - cycles.mean()
    denominator = float(np.dot(centered, centered))
    if denominator == 0.0:
        return 0.0
    slope = float(np.dot(centered, latency - latency.mean())) / denominator
    return slope * window_cycles


def deadline_misses(samples: TimingSamples, period_ns: int) -> int:
    """Cycles that finished after their deadline, release + P."""
    return int(np.count_nonzero(samples.end_ns > samples.release_ns + period_ns))


def skipped_releases(samples: TimingSamples) -> int:
    """Releases that never ran (the skip overrun policy leaves gaps in the cycle numbers)."""
    if len(samples) < 2:
        return 0
    return int(np.sum(np.diff(samples.cycle) - 1))


def late_starts(samples: TimingSamples, period_ns: int) -> int:
    """Cycles that started after the next release was already due (catch-up policy)."""
    return int(np.count_nonzero(samples.start_ns - samples.release_ns >= period_ns))


def jitter_over_fraction(samples: TimingSamples, period_ns: int, fraction: float) -> int:
    """Cycles whose actual period deviates from P by more than ``fraction`` of P."""
    jitter = period_jitter_ns(samples, period_ns)
    return int(np.count_nonzero(np.abs(jitter) > fraction * period_ns))


@dataclass(frozen=True, slots=True)
class TaskTiming:
    """Timing statistics of one task over one run (serialised into ``summary.json``)."""

    period_ns: int
    """Nominal period P."""
    cycles: int
    """Cycles that ran (all of them, before trimming)."""
    trimmed: int
    """Cycles left out of the distributions (the first and last ``trim``)."""
    latency_ns: Distribution
    """Wake-up latency, start − release (as cyclictest)."""
    period_jitter_ns: Distribution
    """Actual period minus P between consecutive cycles."""
    cycle_jitter_ns: Distribution
    """Difference between consecutive actual periods."""
    exec_ns: Distribution
    """Execution time of a cycle, end − start: read inputs, step, publish. The cycle's own
    timing record and status words are written after ``end`` and are not in it (≈1.4 µs)."""
    drift_ns_per_10k_cycles: float
    """Slope of wake-up latency against cycle number, per 10,000 cycles."""
    deadline_misses: int
    """Cycles that ended after release + P (counted over every cycle)."""
    overruns: int
    """Releases skipped (skip policy) or started after the next release (catch-up)."""
    jitter_over_3pct: int
    """Cycles whose period deviated from P by more than 3 % (the thesis criterion)."""

    def to_json(self) -> dict[str, object]:
        out: dict[str, object] = {}
        for key in self.__slots__:
            value = getattr(self, key)
            out[key] = value.to_json() if isinstance(value, Distribution) else value
        return out


def task_timing(
    samples: TimingSamples,
    period_ns: int,
    *,
    trim: int = DEFAULT_TRIM,
    overrun_policy: str = "skip",
) -> TaskTiming:
    """All statistics of one task from its samples."""
    core = samples.trimmed(trim)
    overruns = skipped_releases(samples) if overrun_policy == "skip" else late_starts(samples, period_ns)
    return TaskTiming(
        period_ns=period_ns,
        cycles=len(samples),
        trimmed=2 * trim if len(samples) > 2 * trim else len(samples),
        latency_ns=Distribution.of(wakeup_latency_ns(core)),
        period_jitter_ns=Distribution.of(period_jitter_ns(core, period_ns)),
        cycle_jitter_ns=Distribution.of(cycle_to_cycle_jitter_ns(core)),
        exec_ns=Distribution.of(execution_ns(core)),
        drift_ns_per_10k_cycles=round(drift_ns_per_window(core), 1),
        deadline_misses=deadline_misses(samples, period_ns),
        overruns=overruns,
        jitter_over_3pct=jitter_over_fraction(core, period_ns, THESIS_JITTER_FRACTION),
    )
