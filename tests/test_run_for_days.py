"""Running for days: until stopped, a bounded flight recording, a live summary that survives kill -9,
a full disk that stops the recording and not the run, a watchdog, a policy for misses in a row.

The test tasks run under SCHED_OTHER and unpinned where real-time is not what is tested, so a
spinning or late step does not starve the machine's other real-time work.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import rtloop
from conftest import scaled_ns, scaled_s, unique_name
from rt_test_runnables import Counter, LateFrom, LateOnce, SpinFrom
from rtloop import App, TaskFailed
from rtloop.app.appfile import load_app
from rtloop.errors import AppFileError
from rtloop.ipc.segments import SHM_DIR
from rtloop.record.flight import MAX_PINNED_SEGMENTS, FlightWindow
from rtloop.runtime.session import Limits

MS = 1_000_000


def app_file(tmp_path: Path, name: str, period_ns: int = MS, extra: str = "") -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(
        f'name = "{name}"\n'
        "[tasks.counter]\n"
        'runnable = "rt_test_runnables:Counter"\n'
        f'period_ns = {period_ns}\npolicy = "other"\n{extra}'
        "[record]\nsignals = ['counter.y']\n"
    )
    return path


def wait_for_live_summary(path: Path, timeout_s: float = 30.0) -> dict:
    """The first summary.json rewritten during the run that counts some cycles."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            summary = json.loads(path.read_text())
            if summary["running"] and summary["tasks"]["counter"]["cycles"] > 100:
                return summary
        except (OSError, ValueError, KeyError):
            pass  # not there yet (a half-written file would fail the test below, not here)
        time.sleep(0.1)
    raise AssertionError(f"no live summary with cycles in {path} after {timeout_s} s")


def segments_of(app_name: str) -> list[str]:
    return [p.name for p in SHM_DIR.iterdir() if f"-{app_name}-" in p.name]


def timing_records(path: Path, task: str) -> list[tuple[int, int, int, int]]:
    """(cycle, release_ns, start_ns, end_ns) of every row of ``task`` in timing.csv."""
    with open(path, newline="") as file:
        return [(int(r["cycle"]), int(r["release_ns"]), int(r["start_ns"]), int(r["end_ns"]))
                for r in csv.DictReader(file) if r["task"] == task]


def timing_rows(path: Path, task: str) -> list[int]:
    return [cycle for cycle, *_ in timing_records(path, task)]


# --- until stopped ------------------------------------------------------------------------------
def test_without_duration_it_runs_until_sigint_and_exits_0(tmp_path: Path, rtloop_env) -> None:
    out = tmp_path / "out"
    command = [sys.executable, "-m", "rtloop.cli", "run", str(app_file(tmp_path, unique_name("days_until_sigint"))),
               "--out", str(out)]
    process = subprocess.Popen(command, env=rtloop_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        live = wait_for_live_summary(out / "summary.json")
        assert live["stopped_by"] == "running" and live["duration_s"] is None
        assert live["recording"]["keep_s"] == 60.0  # the default of a run without --duration
        from rtloop.report.data import load_run

        assert load_run(out).tasks["counter"]["cycles"] > 100  # `rtloop report` reads a live run
        from rtloop.toolbox.monitor import Monitor

        views = Monitor(unique_name("days_until_sigint")).snapshot()  # and `rtloop top` shows what it says
        assert len(views) == 1 and "counter p99" in views[0].summary_line
        time.sleep(1.0)
        assert process.poll() is None, "it stopped by itself"
    finally:
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr
    assert "stopped by signal" in stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["running"] is False and summary["stopped_by"] == "signal"
    assert summary["tasks"]["counter"]["cycles"] > live["tasks"]["counter"]["cycles"]
    rows = timing_rows(out / "timing.csv", "counter")
    assert rows and rows[-1] >= summary["tasks"]["counter"]["cycles"] - 1
    assert not (out / "segments").exists() and not (out / ".summary-reserve").exists()


def test_simulate_still_needs_a_duration(tmp_path: Path, rtloop_env) -> None:
    command = [sys.executable, "-m", "rtloop.cli", "simulate", str(app_file(tmp_path, "days_sim_needs")),
               "--out", str(tmp_path / "out")]
    result = subprocess.run(command, env=rtloop_env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "needs --duration" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize("value", ["0", "-1", "abc", "inf"])
def test_keep_and_duration_reject_what_is_not_positive_seconds(tmp_path: Path, rtloop_env, value: str) -> None:
    command = [sys.executable, "-m", "rtloop.cli", "run", str(app_file(tmp_path, "days_bad_keep")),
               "--out", str(tmp_path / "out"), "--keep", value]
    result = subprocess.run(command, env=rtloop_env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "--keep" in result.stderr and "Traceback" not in result.stderr


# --- kill -9 --------------------------------------------------------------------------------------
def test_kill_9_of_the_supervisor_leaves_a_parseable_summary(tmp_path: Path, rtloop_env) -> None:
    out = tmp_path / "out"
    command = [sys.executable, "-m", "rtloop.cli", "run", str(app_file(tmp_path, unique_name("days_kill9"))),
               "--out", str(out)]
    process = subprocess.Popen(command, env=rtloop_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        first = wait_for_live_summary(out / "summary.json")
        # a rewrite after that one, 1 s of counting in it (every 2 s: however late a loaded machine runs
        # the supervisor), then the kill half an interval on, where it may land in the middle of the next
        deadline = time.monotonic() + 60
        while ((summary := json.loads((out / "summary.json").read_text()))["elapsed_s"] <= max(1.0, first["elapsed_s"])
               or summary["tasks"]["counter"]["cycles"] <= 1000):
            assert time.monotonic() < deadline, f"summary.json was not rewritten within 60 s: {summary}"
            time.sleep(0.1)
        time.sleep(1.0)
    finally:
        process.kill()
        process.wait(timeout=30)
    summary = json.loads((out / "summary.json").read_text())  # whole, never half written
    assert summary["running"] is True and summary["tasks"]["counter"]["cycles"] > 1000
    assert summary["elapsed_s"] > 1.0


# --- the flight recorder ----------------------------------------------------------------------------
@pytest.mark.rt
def test_keep_bounds_the_files_and_keeps_the_cycles_around_a_miss(tmp_path: Path, monkeypatch) -> None:
    # 20 segments of a quarter of a second (the recorder's shortest is 1 s; shortened here, the
    # run is the same in every other respect): more than the pinned budget and the window
    # together, even if a loaded machine makes every segment miss a deadline somewhere; the
    # miss comes in the third segment, before the pin budget can be spent
    from rtloop.record import flight

    # the same 2,500 cycles wherever it runs: at 2 ms unstretched, the emulated guest skipped most
    # releases around the miss, and the cycles before it were not there to keep
    monkeypatch.setattr(flight, "MIN_SEGMENT_NS", scaled_ns(250_000_000))
    period_ns, late_from, duration_s, keep_s = scaled_ns(2 * MS), 250, scaled_s(5.0), scaled_s(0.5)
    app = App(unique_name("days_keep_bounds"))
    late = app.add_task("late", LateOnce(late_from), period_ns=period_ns, priority=50, cpu=0)
    app.record(late.y)
    summary = rtloop.run(app, duration_s, tmp_path, keep_s=keep_s)

    rows = timing_records(tmp_path / "timing.csv", "late")
    cycles = [cycle for cycle, *_ in rows]
    task = summary.tasks["late"].timing
    recording = summary.recording
    assert recording["keep_s"] == keep_s and recording["events"] >= 1 and recording["stopped"] is None
    # the last keep_s seconds are there, up to the last cycle
    assert max(cycles) >= duration_s * 1e9 / period_ns - 3
    keep_cycles = int(keep_s * 1e9 / period_ns)
    assert len([c for c in cycles if c > max(cycles) - keep_cycles]) >= keep_cycles - task.overruns
    # the miss, long before the window, is there with what came before and after it
    late_cycle = next(c for c, release, _start, end in rows if c >= late_from and end - release >= 3 * period_ns)
    assert late_cycle < max(cycles) - 3 * keep_cycles
    assert any(late_cycle - 20 <= c < late_cycle for c in cycles)
    assert any(late_cycle < c <= late_cycle + 20 for c in cycles)
    # and the rest is bounded: window segments plus the pinned ones, never everything
    segment_cycles = recording["segment_s"] * 1e9 / period_ns
    bound = (keep_s / recording["segment_s"] + 2 + recording["pinned_segments"]) * segment_cycles * 1.2
    assert len(cycles) <= bound
    assert len(cycles) < task.cycles
    signal_rows = (tmp_path / "signals.csv").read_text().splitlines()
    assert 1 < len(signal_rows) < task.cycles
    assert not (tmp_path / "segments").exists()


def test_run_mcap_of_a_kept_window_reads_back(tmp_path: Path, monkeypatch) -> None:
    pytest.importorskip("mcap")
    from mcap.reader import make_reader

    from rtloop.record import flight

    monkeypatch.setattr(flight, "MIN_SEGMENT_NS", 250_000_000)  # 8 segments in 2 s: the early ones dropped
    app = App(unique_name("days_keep_mcap"))
    counter = app.add_task("counter", Counter(), period_ns=2 * MS, policy="other")
    app.record(counter.y)
    rtloop.run(app, 2.0, tmp_path, keep_s=0.5)
    with open(tmp_path / "run.mcap", "rb") as file:
        topics = [channel.topic for _schema, channel, _message in make_reader(file).iter_messages()]
    kept = len(timing_rows(tmp_path / "timing.csv", "counter"))
    assert topics.count("/rtloop/timing/counter") == kept > 0
    assert topics.count("/rtloop/signals") == len((tmp_path / "signals.csv").read_text().splitlines()) - 1


def test_flight_window_prunes_old_segments_and_pins_around_events(tmp_path: Path) -> None:
    window = FlightWindow(tmp_path, keep_s=6.0)  # 1 s segments
    second = 1_000_000_000
    names = ["timing.csv"]
    for t in range(1, 30):
        window.path("timing.csv").write_text("header\n" + f"{t}\n")
        if t == 10:
            window.mark_event()
        window.rotate(t * second, names)
    kept = sorted(int(p.name.split("-")[0]) for p in window.directory.iterdir())
    assert kept[:3] == [8, 9, 10]  # before, during and after the event (segment k starts at k s)
    # the last 6 s (segment 29 has just begun) and the segment before: its task snapshots start their replay
    assert kept[3:] == list(range(22, 29))
    window.path("timing.csv").write_text("header\nlast\n")
    window.stitch(tmp_path, names)
    lines = (tmp_path / "timing.csv").read_text().splitlines()
    assert lines[0] == "header" and lines[-1] == "last" and "header" not in lines[1:]
    assert not window.directory.exists()


def test_flight_window_pins_at_most_its_budget(tmp_path: Path) -> None:
    window = FlightWindow(tmp_path, keep_s=6.0)
    for t in range(1, 200):
        window.mark_event()
        window.rotate(t * 1_000_000_000, [])
    assert sum(s.pinned for s in window.segments) <= MAX_PINNED_SEGMENTS
    assert window.events == 199 and window.events_not_kept > 150
    assert len(window.segments) <= MAX_PINNED_SEGMENTS + 9


# --- a full disk ------------------------------------------------------------------------------------
def fill_the_disk(filler: Path) -> None:
    """Takes every free block of the filesystem in one ``fallocate``, which takes all it asks for or
    nothing, and then nothing more. Written block by block until ENOSPC instead, the filler raced
    the run: the run's first write failing on the full disk makes it give up its summary's reserve,
    and the filler's next blocks took that (on a loaded machine: the final summary then found no
    room, and summary.json kept saying 'running')."""
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        for _ in range(1000):
            stat = os.statvfs(filler)
            try:
                os.posix_fallocate(fd, 0, stat.f_bavail * stat.f_frsize)
                return
            except OSError:  # ENOSPC: the run wrote since, ask again for what is left
                continue
        raise AssertionError("the run kept writing: the disk was never filled in one go")
    finally:
        os.close(fd)


@pytest.mark.skipif(os.geteuid() != 0, reason="mounting a tiny tmpfs needs root")
def test_a_full_disk_stops_the_recording_not_the_run(tmp_path: Path, rtloop_env) -> None:
    disk = tmp_path / "tiny"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(disk)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.strip()}")
    try:
        name = unique_name("days_disk_full")
        out = disk / "out"
        command = [sys.executable, "-m", "rtloop.cli", "run", str(app_file(tmp_path, name)), "--duration", "4",
                   "--out", str(out)]
        # The run starts with room for its whole recording (it is refused otherwise), then something
        # else fills the disk under it: the filler below, once the run has written its first summary.
        run = subprocess.Popen(command, env=rtloop_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 60
        while not (out / "summary.json").exists():
            assert run.poll() is None and time.monotonic() < deadline, run.communicate()
            time.sleep(0.02)
        fill_the_disk(disk / "filler")
        stdout, stderr = run.communicate(timeout=120)
        result = subprocess.CompletedProcess(command, run.returncode, stdout, stderr)
        assert result.returncode == 0, result.stderr
        assert "Traceback" not in result.stderr
        assert "recording stopped" in result.stderr and "ENOSPC" in result.stderr
        summary = json.loads((out / "summary.json").read_text())
        assert "ENOSPC" in summary["recording"]["stopped"]
        assert summary["stopped_by"] == "duration"
        counter = summary["tasks"]["counter"]
        assert counter["cycles"] + counter["overruns"] >= 3900  # the loop ran on to the end
        assert segments_of(name) == []
        assert not (out / ".summary-reserve").exists()
    finally:
        subprocess.run(["umount", str(disk)], check=False)


# --- watchdog and misses in a row -------------------------------------------------------------------
def test_watchdog_stops_the_app_when_a_step_spins(tmp_path: Path) -> None:
    stuck_file = tmp_path / "stuck_cycle"
    app = App(unique_name("days_watchdog"))
    app.add_task("spinner", SpinFrom(30, str(stuck_file)), period_ns=10 * MS, policy="other", watchdog_periods=50)
    app.add_task("counter", Counter(), period_ns=10 * MS, policy="other")
    started = time.monotonic()
    with pytest.raises(TaskFailed) as failed:  # (a shorter least wait than a run's 10 s: this test's time)
        rtloop.run(app, 60.0, tmp_path / "out", limits=Limits(watchdog_min_s=2.0, watchdog_grace_s=1.0))
    assert time.monotonic() - started < 45, "the watchdog ended the run, not its duration"
    error = failed.value
    assert error.task == "spinner" and error.phase == "step"
    assert error.cycle == int(stuck_file.read_text())
    assert "watchdog" in error.reason and "SIGKILL" in error.reason
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["stopped_by"] == "watchdog" and summary["failure"]["task"] == "spinner"
    assert summary["tasks"]["counter"]["cycles"] > 30  # the other task stopped the orderly way
    assert segments_of(unique_name("days_watchdog")) == []


def test_max_consecutive_misses_stops_the_app(tmp_path: Path) -> None:
    app = App(unique_name("days_misses_in_a_row"))
    app.add_task("late", LateFrom(20), period_ns=5 * MS, policy="other", max_consecutive_misses=3)
    with pytest.raises(TaskFailed) as failed:
        rtloop.run(app, 30.0, tmp_path)
    assert failed.value.task == "late" and failed.value.phase == "step"
    assert "3 deadline misses in a row" in failed.value.reason
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["stopped_by"] == "fault" and summary["tasks"]["late"]["misses_in_a_row_max"] == 3
    # It stopped at the first third miss in a row, read from the recorded cycles (a miss: the step
    # ended past the next release). LateFrom makes them from cycle 20 on; a loaded machine may make
    # three before that (SCHED_OTHER at 5 ms), and the app must stop there then, so the cycle is
    # not asserted.
    with open(tmp_path / "timing.csv") as file:
        rows = [row for row in csv.DictReader(file) if row["task"] == "late"]
    missed = [int(row["end_ns"]) > int(row["release_ns"]) + 5 * MS for row in rows]
    in_a_row = [missed[k - 2] and missed[k - 1] and missed[k] for k in range(2, len(missed))]
    assert int(rows[-1]["cycle"]) == failed.value.cycle, "the failing cycle is the last one recorded"
    assert in_a_row and in_a_row[-1] and not any(in_a_row[:-1]), missed
    assert sum(int(row["cycle"]) >= 20 for row in rows) <= 3, "LateFrom's third miss stops it at the latest"


def test_misses_in_a_row_are_counted_and_the_run_goes_on_by_default(tmp_path: Path) -> None:
    app = App(unique_name("days_misses_go_on"))
    app.add_task("late", LateFrom(20), period_ns=5 * MS, policy="other")
    summary = rtloop.run(app, 1.0, tmp_path)
    assert summary.stopped_by == "duration"
    assert summary.tasks["late"].misses_in_a_row_max >= 10


def test_app_file_takes_the_watchdog_and_miss_policy(tmp_path: Path) -> None:
    extra = "watchdog_periods = 0\nmax_consecutive_misses = 5\n"
    config = load_app(app_file(tmp_path, "days_appfile", extra=extra)).tasks["counter"].config
    assert (config.watchdog_periods, config.max_consecutive_misses) == (0, 5)
    with pytest.raises(AppFileError, match="max_consecutive_misses"):
        load_app(app_file(tmp_path, "days_appfile_bad", extra="max_consecutive_misses = 0\n"))
