"""Statistics on synthetic timings whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest

from rtloop.stats.timing import (
    Distribution,
    TimingSamples,
    cycle_to_cycle_jitter_ns,
    deadline_misses,
    drift_ns_per_window,
    period_jitter_ns,
    skipped_releases,
    task_timing,
)

P = 1_000_000


def samples(latency_ns, exec_ns=1_000, cycles=None, t0=10**12) -> TimingSamples:
    latency = np.asarray(latency_ns, dtype=np.int64)
    n = latency.size
    cycle = np.arange(n, dtype=np.int64) if cycles is None else np.asarray(cycles, dtype=np.int64)
    release = t0 + cycle * P
    start = release + latency
    end = start + np.broadcast_to(np.asarray(exec_ns, dtype=np.int64), (n,))
    return TimingSamples(cycle, release, start, end)


def test_constant_latency_has_no_jitter_and_no_drift() -> None:
    s = samples([5_000] * 100)
    stats = task_timing(s, P, trim=0)
    assert stats.latency_ns.min == stats.latency_ns.max == 5_000
    assert stats.period_jitter_ns.max == 0 and stats.period_jitter_ns.min == 0
    assert stats.drift_ns_per_10k_cycles == 0
    assert stats.deadline_misses == 0 and stats.overruns == 0 and stats.jitter_over_3pct == 0
    assert stats.cycles == 100


def test_one_late_wakeup_shows_in_latency_jitter_and_3pct() -> None:
    latency = [2_000] * 50
    latency[30] = 2_000 + 50_000  # 5 % of the period late
    s = samples(latency)
    assert list(period_jitter_ns(s, P)[28:31]) == [0, 50_000, -50_000]
    stats = task_timing(s, P, trim=0)
    assert stats.latency_ns.max == 52_000
    assert stats.jitter_over_3pct == 2  # the long period and the short one after it
    assert list(cycle_to_cycle_jitter_ns(s)[28:30]) == [50_000, -100_000]


def test_trimming_removes_first_and_last_cycles() -> None:
    latency = [1_000] * 100
    latency[0] = latency[-1] = 900_000
    stats = task_timing(samples(latency), P, trim=20)
    assert stats.latency_ns.max == 1_000
    assert stats.trimmed == 40
    assert stats.cycles == 100


def test_trimming_everything_gives_nan_not_an_error() -> None:
    stats = task_timing(samples([1_000] * 10), P, trim=20)
    assert np.isnan(stats.latency_ns.p50)
    assert stats.to_json()["latency_ns"]["p50"] is None


def test_deadline_misses_count_cycles_ending_after_release_plus_period() -> None:
    exec_ns = np.full(10, 100_000)
    exec_ns[[2, 7]] = P  # start latency 1000 + P → ends after the deadline
    assert deadline_misses(samples([1_000] * 10, exec_ns=exec_ns), P) == 2


def test_skipped_releases_are_overruns_and_excluded_from_jitter() -> None:
    s = samples([1_000] * 6, cycles=[0, 1, 2, 5, 6, 7])
    assert skipped_releases(s) == 2
    assert list(period_jitter_ns(s, P)) == [0, 0, 0, 0]  # the 3-period gap is not "jitter"
    assert task_timing(s, P, trim=0, overrun_policy="skip").overruns == 2


def test_drift_of_a_relative_sleep_loop_is_measured() -> None:
    # A loop that sleeps P after its work drifts by its overhead every cycle.
    latency = np.arange(20_000) * 30  # 30 ns later every cycle
    assert drift_ns_per_window(samples(latency)) == pytest.approx(300_000, rel=1e-9)


def test_percentiles_match_numpy() -> None:
    rng = np.random.default_rng(1)
    values = rng.integers(1_000, 90_000, 5_000)
    d = Distribution.of(values)
    assert d.p99 == pytest.approx(np.percentile(values, 99))
    assert d.p999 == pytest.approx(np.percentile(values, 99.9))
    assert d.mean == pytest.approx(values.mean())


def test_from_records_sorts_by_cycle() -> None:
    records = np.array([[1, 20, 21, 22], [0, 10, 11, 12]])
    s = TimingSamples.from_records(records)
    assert list(s.cycle) == [0, 1] and list(s.release_ns) == [10, 20]


def test_json_has_the_contract_fields() -> None:
    stats = task_timing(samples([1_000] * 100), P).to_json()
    for key in ("cycles", "trimmed", "latency_ns", "period_jitter_ns", "exec_ns", "deadline_misses",
                "overruns", "jitter_over_3pct"):
        assert key in stats
    assert set(stats["latency_ns"]) >= {"min", "mean", "p50", "p99", "p999", "max"}
