"""Run artifacts → the numbers a report plots (pure functions, no plotting).

Runs are read by :func:`rtloop.load` (numpy arrays, memory-mapped when large); everything
here recomputes the distributions with the *same* functions and the
same trimming as ``summary.json`` (:mod:`rtloop.stats.timing`), so a histogram's extremes and
sample count agree with the summary table printed beside it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from rtloop.errors import RtloopError
from rtloop.record.load import LoadError, RunData, Signals, load
from rtloop.stats import timing

FloatArray = npt.NDArray[np.float64]
HISTOGRAM_BINS = 100
TAIL_QUANTILE = 0.999
"""Histograms span at least the central 99.8 %; a far-out extreme is counted and shown by an arrow."""


class ReportError(RtloopError, ValueError):
    """A run directory cannot be reported on (missing, or without a readable summary)."""


@dataclass(frozen=True)
class Run:
    """One run directory, loaded by :func:`rtloop.load`, with the label the report gives it."""

    data: RunData
    """The run as :func:`rtloop.load` returns it."""
    label: str
    """Short name for legends and table headers (the directory name, made unique)."""

    @property
    def path(self) -> Path:
        """The run directory."""
        return self.data.path

    @property
    def summary(self) -> dict[str, Any]:
        """``summary.json`` as parsed."""
        return self.data.summary

    @property
    def samples(self) -> dict[str, timing.TimingSamples]:
        """Per task, every cycle of ``timing.csv`` (untrimmed)."""
        return self.data.timing

    @property
    def signals(self) -> Signals | None:
        """``signals.csv`` if present and non-empty."""
        signals = self.data.signals
        return signals if signals is not None and signals.rows else None

    @property
    def problems(self) -> list[str]:
        """Things a reader should know (empty timing.csv, row counts that disagree, ...)."""
        problems = list(self.data.problems)
        if self.data.signals is not None and not self.data.signals.rows:
            problems.append("signals.csv has no rows")
        return problems

    @property
    def failure(self) -> dict[str, Any] | None:
        """The failure that stopped the run, if any."""
        return self.data.failure

    @property
    def tasks(self) -> dict[str, dict[str, Any]]:
        """Per-task entries of ``summary.json``."""
        return self.data.tasks

    @property
    def simulated(self) -> bool:
        """A run of ``rtloop simulate``: its clock is simulated, so it has no timing to show."""
        return self.summary.get("mode") == "simulate"

    @property
    def non_rt_tasks(self) -> list[str]:
        """Tasks that ran without a real-time policy (their numbers are not RT numbers)."""
        if self.summary.get("mode") == "simulate":
            return []
        return [name for name, task in self.tasks.items() if not task.get("rt", False)]


def load_run(path: Path, label: str | None = None) -> Run:
    """Load one run directory; raise :class:`ReportError` naming what is missing."""
    try:
        data = load(path)
    except LoadError as error:
        raise ReportError(str(error)) from None
    return Run(data, label or Path(path).resolve().name)


# --- what a task's figures show ---------------------------------------------------------
@dataclass(frozen=True)
class TaskSeries:
    """One task's per-cycle numbers, trimmed exactly as ``summary.json`` trims them."""

    period_ns: int
    """Nominal period P."""
    trim: int
    """Cycles left out at each end."""
    all_samples: timing.TimingSamples
    """Every recorded cycle (for the over-time plot, which shades the trimmed ends)."""
    latency_ns: npt.NDArray[np.int64]
    """Wake-up latency of each kept cycle, start − release."""
    period_jitter_ns: npt.NDArray[np.int64]
    """Actual period − P between consecutive kept cycles."""
    exec_ns: npt.NDArray[np.int64]
    """Execution time of each kept cycle, end − start."""


def task_series(run: Run, task: str) -> TaskSeries:
    """The distributions of ``task`` in ``run``, with the trimming recorded in its summary."""
    entry = run.tasks.get(task, {})
    samples = run.samples.get(task, timing.TimingSamples.from_records(np.zeros((0, 4), dtype=np.int64)))
    period_ns = int(entry.get("period_ns") or 0)
    cycles = len(samples)
    trimmed = int(entry.get("trimmed", 2 * timing.DEFAULT_TRIM))
    # summary.json stores the total left out (half at each end); when it equals every
    # cycle, nothing was kept, whatever the per-end trim was.
    trim = cycles if cycles and trimmed >= cycles else trimmed // 2
    core = samples.trimmed(trim)
    return TaskSeries(
        period_ns=period_ns,
        trim=trim,
        all_samples=samples,
        latency_ns=timing.wakeup_latency_ns(core),
        period_jitter_ns=timing.period_jitter_ns(core, period_ns) if period_ns else np.zeros(0, np.int64),
        exec_ns=timing.execution_ns(core),
    )


@dataclass(frozen=True)
class Histogram:
    """What a histogram shows: counts over edges, plus what fell outside them."""

    counts: npt.NDArray[np.int64]
    """Samples per bin."""
    edges_ns: FloatArray
    """Bin edges (len(counts) + 1), nanoseconds."""
    below: int
    """Samples left of the first edge (shown by an arrow, not a bar)."""
    above: int
    """Samples right of the last edge."""
    n: int
    """All samples: ``counts.sum() + below + above``."""
    min_ns: float
    """Smallest sample (NaN if none)."""
    max_ns: float
    """Largest sample (NaN if none)."""


def histogram(values: npt.ArrayLike, *, include_ns: tuple[float, ...] = (), bins: int = HISTOGRAM_BINS) -> Histogram:
    """Histogram of ``values`` over a range that shows the bulk and the given marks.

    The range covers every sample unless an extreme lies far beyond the 0.1 %/99.9 %
    quantiles (one 260 ms stall would squash a 30 µs distribution into one bar); then
    it stops shortly past the quantile and the samples beyond are counted in
    ``below``/``above``. ``include_ns`` (e.g. the ±3 % lines) is always in range.
    """
    data = np.asarray(values, dtype=np.float64)
    if data.size == 0:
        return Histogram(np.zeros(0, np.int64), np.zeros(1), 0, 0, 0, math.nan, math.nan)
    ordered = np.sort(data)
    n = ordered.size
    lo_all, hi_all = float(ordered[0]), float(ordered[-1])
    # The bulk: all but the k smallest and k largest samples (k ≥ 1, so that a single
    # outlier among few samples cannot stretch the bulk the way an interpolated quantile does).
    k = max(1, math.ceil((1 - TAIL_QUANTILE) * n))
    q_lo, q_hi = (float(ordered[k]), float(ordered[n - 1 - k])) if n > 2 * k + 1 else (lo_all, hi_all)
    span = max(q_hi - q_lo, 1.0)
    lo = lo_all if lo_all >= q_lo - span else q_lo - 0.1 * span
    hi = hi_all if hi_all <= q_hi + span else q_hi + 0.1 * span
    lo, hi = min([lo, *include_ns]), max([hi, *include_ns])
    if hi - lo < 1.0:  # all samples equal (e.g. a simulation): ±1 µs around them
        lo, hi = lo - 1000.0, hi + 1000.0
    edges = np.linspace(lo, hi, bins + 1)
    counts, _ = np.histogram(data, bins=edges)
    below = int(np.count_nonzero(data < lo))
    above = int(np.count_nonzero(data > hi))
    return Histogram(counts.astype(np.int64), edges, below, above, int(data.size), lo_all, hi_all)


def run_labels(paths: list[Path]) -> list[str]:
    """Short unique labels: directory names, with the parent added where names repeat."""
    names = [Path(p).resolve().name for p in paths]
    if len(set(names)) == len(names):
        return names
    return [f"{Path(p).resolve().parent.name}/{Path(p).resolve().name}" for p in paths]
