"""Times in CSV files read back to the nanosecond however long the run (issue 29): ``t_s`` was written
as ``t_ns / 1e9``, whose shortest text stops telling neighbouring nanoseconds apart after 2^53 ns
(104 days), and read as ``round(float(text) * 1e9)``; device playback then found rows between
releases and left those cycles without readings."""

from __future__ import annotations

import csv
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest

from rtloop import App
from rtloop.app.profiles import load_profile
from rtloop.app.specs import SignalRef
from rtloop.record.csvfiles import SignalsCsv
from rtloop.seconds import ns_from_seconds, seconds_text

P = 3_000_017  # a period whose multiples have every digit
LATE = 40_000_000_000  # ticks: 1.2e17 ns, 3.8 years into a run


def test_seconds_text_is_exact_both_ways() -> None:
    for t_ns in (0, 1, 10_000_000, 999_999_999, 1_000_000_000, 2**53 + 1, 123_456_789_123_456_789, -1_500):
        text = seconds_text(t_ns)
        assert Decimal(text) * 10**9 == t_ns and ns_from_seconds(text) == t_ns, (t_ns, text)
    assert seconds_text(10_000_000) == "0.01" and seconds_text(0) == "0.0" and seconds_text(3 * 10**9) == "3.0"
    assert ns_from_seconds("1e-05") == 10_000  # a float's shortest text, as earlier files hold
    for bad in ("nan", "inf", "", "1,5"):
        with pytest.raises(ValueError):
            ns_from_seconds(bad)


def test_signals_csv_times_read_back_to_the_nanosecond_years_into_a_run(tmp_path: Path) -> None:
    path = tmp_path / "signals.csv"
    writer = SignalsCsv(path, [SignalRef("a", "y", 0, 1)], {"a": P}, {"a": 1})
    ticks = LATE + np.arange(2000)
    writer.add("a", ticks, np.arange(2000, dtype=np.float64)[:, None])
    writer.flush(final=True)
    writer.close()
    with open(path, newline="") as file:
        rows = list(csv.reader(file))[1:]
    wrong = [(row[0], (k + 1) * P) for row, k in zip(rows, ticks.tolist(), strict=True)
             if Decimal(row[0]) * 10**9 != (k + 1) * P]
    assert not wrong, f"{len(wrong)} of {len(rows)} rows' t_s are not their time, e.g. {wrong[:3]}"


def test_device_playback_finds_every_release_years_into_a_run(tmp_path: Path) -> None:
    """``rtloop replay`` puts in a device's place what it read, by cycle, from the rows at releases."""
    from device_test_drivers import Echo
    from rtloop.runtime.replay.logs import play_back_devices

    app = App("exact_times")
    ctl = app.add_task("ctl", Echo(), period_ns=P)
    dev = app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(tmp_path / "dev.log"),
                         limits={"c0": {"min": -1e9, "max": 1e9, "safe": 0.0}})
    app.connect(ctl.y[0], dev.u[0])
    app.connect(dev.y[0], ctl.u[0])
    cycles = list(range(LATE, LATE + 500))
    lines = ["t_s,ctl.u[0]"] + [f"{seconds_text(k * P)},{float(k - LATE)!r}" for k in cycles]
    (tmp_path / "signals.csv").write_text("\n".join(lines) + "\n")
    play_back_devices(app, tmp_path)
    readings = app.devices["dev"].twin.readings
    missing = [k for k in cycles if k not in readings]
    assert not missing, f"{len(missing)} of {len(cycles)} cycles without their reading, e.g. {missing[:3]}"
    assert [readings[k][0] for k in cycles] == [float(k - LATE) for k in cycles]


def test_a_feed_file_keeps_its_times_to_the_nanosecond(tmp_path: Path) -> None:
    path = tmp_path / "feed.csv"
    path.write_text("t_s,v\n0.0,1.0\n123456789.123456789,2.0\n123456789.123456791,3.0\n")
    t_ns, _values = load_profile(path, 1, "ports.feed")
    assert t_ns.tolist() == [0, 123_456_789_123_456_789, 123_456_789_123_456_791]

