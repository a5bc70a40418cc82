"""A replay honours what the run lost on the way (summary.json ``recording.lost``).

A run whose supervisor fell behind loses records: timing records (the cycles it ran), signal
rows (empty cells in signals.csv), port values it took but could not log, stale reads its read
log dropped. The replay says so, with where, compares what the files do hold, and never calls
the result equal over data it does not have. Each run here is a simulation whose files are then
given the marks a loss leaves (the counts in the summary, the rows or cells missing), as the
recorder writes them.
"""

from __future__ import annotations

import csv
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name
from replay_helpers import PERIOD_NS, pi_loop_app

P = PERIOD_NS  # the controller's period (the plant's is 2 P)


def _run(tmp_path: Path, name: str, seconds: float = 0.2) -> Path:
    writes = {("controller", 30): [("setpoint", [1.0, -1.0])]}
    rtloop.simulate(pi_loop_app(name), seconds, tmp_path / "run", port_writes=writes)
    (tmp_path / "run" / "inputs.csv").write_text("task,cycle,port,values\ncontroller,30,setpoint,1.0 -1.0\n")
    return tmp_path / "run"


def _lose(run: Path, **lost: dict[str, int]) -> None:
    """Put the counts of what was lost in the run's summary, as the run engine writes them."""
    path = run / "summary.json"
    summary = json.loads(path.read_text())
    recording = summary.setdefault("recording", {})
    for kind, counts in lost.items():
        if kind in ("reads_dropped", "stopped"):
            recording[kind] = counts
        else:
            recording.setdefault("lost", {})[kind] = counts
    path.write_text(json.dumps(summary))


def _rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as file:
        return list(csv.reader(file))


def _write_rows(path: Path, rows: list[list[str]]) -> None:
    path.write_text("".join(",".join(cells) + "\n" for cells in rows))


def _drop_timing(run: Path, task: str, cycles: set[int]) -> None:
    rows = _rows(run / "timing.csv")
    _write_rows(run / "timing.csv", [row for row in rows if not (row[0] == task and int(row[1]) in cycles)])


def test_without_losses_the_same_run_replays_equal(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    result = replay(_run(tmp_path, "lost_none"), tmp_path / "replay", app=pi_loop_app("lost_none"))
    assert result.equal and not result.lost and result.rows_compared == result.rows_in_run == 201


def test_lost_signal_rows_are_named_left_out_of_the_comparison_and_never_called_equal(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    run = _run(tmp_path, "lost_rows")
    rows = _rows(run / "signals.csv")
    columns = [rows[0].index("plant.y[0]"), rows[0].index("plant.y[1]")]
    for row in rows[51:55]:  # t = 0.050..0.053 s: the recorder leaves a lost value's cells empty
        for column in columns:
            row[column] = ""
    _write_rows(run / "signals.csv", rows)
    _lose(run, signal_rows={"plant": 2})
    result = replay(run, tmp_path / "replay", app=pi_loop_app("lost_rows"))
    assert not result.equal and result.divergence is None and result.cannot is None
    assert result.rows_compared == result.rows_in_run == 201, "every row compared, the lost cells left out"
    assert result.lost == ("signals.csv: 4 rows from t = 0.05 s to 0.053 s hold cells the run lost "
                           "(plant.y[0], plant.y[1]; recording.lost.signal_rows: plant 2): those cells are not "
                           "compared",)

    rows[151][columns[0]] = "0.125"  # a real difference after the gap is still found
    _write_rows(run / "signals.csv", rows)
    later = replay(run, tmp_path / "again", app=pi_loop_app("lost_rows"))
    assert later.divergence is not None and later.divergence.t_s == 0.15 and later.rows_compared == 150
    assert later.lost == result.lost


def test_a_gap_after_an_overrun_with_timing_records_lost_cannot_be_told_from_skipped_releases(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    run = _run(tmp_path, "lost_gap")
    rows = _rows(run / "timing.csv")
    for row in rows:  # plant cycle 19 overran: a gap after it may be skipped releases
        if row[:2] == ["plant", "19"]:
            row[4] = str(int(row[2]) + 3 * 2 * P)
    _write_rows(run / "timing.csv", rows)
    _drop_timing(run, "plant", {20, 21})
    _lose(run, timing_records={"plant": 2})
    result = replay(run, tmp_path / "replay", app=pi_loop_app("lost_gap"))
    assert not result.equal
    assert result.cannot == ("from t = 0.04 s: timing.csv lacks plant cycles 20..21 after an overrun, and the run "
                             "lost 2 of plant's timing records (recording.lost): skipped releases or lost cycles, "
                             "the replay cannot tell which")
    assert result.rows_compared == result.rows_in_run == 40 and result.divergence is None


def test_timing_records_lost_after_the_last_one_kept_end_the_comparison_there(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    run = _run(tmp_path, "lost_end")
    _drop_timing(run, "plant", {97, 98, 99})
    _lose(run, timing_records={"plant": 3})
    result = replay(run, tmp_path / "replay", app=pi_loop_app("lost_end"))
    assert not result.equal
    assert result.cannot == ("from t = 0.194 s: the run lost 3 of plant's timing records (recording.lost) and "
                             "timing.csv shows no gap in its cycles: they were lost after its last record (cycle "
                             "96), so the replay follows plant only up to there")
    assert result.rows_compared == result.rows_in_run == 194


def test_unlogged_port_values_dropped_reads_and_a_stopped_recording_are_named(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    run = _run(tmp_path, "lost_inputs")
    (run / "inputs.csv").write_text("task,cycle,port,values\n")  # the write at cycle 30 was taken, not logged
    _lose(run, inputs={"controller": 1}, reads_dropped={"plant": 4}, stopped="disk full")
    result = replay(run, tmp_path / "replay", app=pi_loop_app("lost_inputs"))
    assert not result.equal
    assert result.lost == (
        "the run took 1 values from ports of controller that it did not log (recording.lost.inputs: its input log "
        "was full): the replay cannot feed them, and the run does not say when they came, so rows may differ from "
        "then on",
        "the run's read log of plant dropped 4 stale connection reads (recording.reads_dropped: ring full): the "
        "replay reads what logical execution time promised there instead",
        "the recording stopped during the run (disk full): its files end there (timing.csv holds every task up to "
        "t = 0.2 s), what was recorded is replayed and compared, the rest of the run is not")
    assert result.divergence is not None and result.divergence.task == "controller", "the unlogged write shows"


def test_the_cli_says_what_was_lost_and_exits_1_a_garbled_count_is_bad_input(tmp_path: Path, rtloop_env) -> None:
    app_file = tmp_path / "lost_cli.toml"
    app_file.write_text(f'name = "{unique_name("lost_cli")}"\n[tasks.a]\nrunnable = "rt_test_runnables:Integrator"\n'
                        'period_ns = 1_000_000\n[record]\nsignals = ["a.y"]\n')
    env = rtloop_env
    cli = [sys.executable, "-m", "rtloop.cli"]
    subprocess.run([*cli, "run", str(app_file), "--duration", "0.3", "--out", str(tmp_path / "run"), "-q"], env=env,
                   check=True, capture_output=True, timeout=300)
    rows = _rows(tmp_path / "run" / "signals.csv")
    rows[100][1] = ""
    _write_rows(tmp_path / "run" / "signals.csv", rows)
    _lose(tmp_path / "run", signal_rows={"a": 1})
    done = subprocess.run([*cli, "replay", str(tmp_path / "run"), "--out", str(tmp_path / "replay")], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "equal where it kept their values" in done.stderr and "not called equal" in done.stderr
    assert "  lost: signals.csv: 1 rows from t = " in done.stderr
    # the run may skip a release when the machine stalls it (1 kHz): the replay follows it, and says so
    followed = r"\(\d+ skipped releases?, 0 stale connection reads and 0 port inputs followed\)"
    assert re.search(followed, done.stderr), done.stderr
    _lose(tmp_path / "run", signal_rows={"a": "many"})
    done = subprocess.run([*cli, "replay", str(tmp_path / "run"), "--out", str(tmp_path / "again")], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and "recording.lost is not counts per kind and task" in done.stderr
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr


@pytest.mark.parametrize("garbled", [[1, 2], {"plant": None}, "all"])
def test_a_garbled_recording_lost_is_one_clear_error(tmp_path: Path, garbled) -> None:
    from rtloop.errors import AppError
    from rtloop.runtime.replay import replay

    run = _run(tmp_path, "lost_garbled", 0.02)
    _lose(run, timing_records=garbled)
    with pytest.raises(AppError, match=r"recording\.lost is not counts per kind and task"):
        replay(run, tmp_path / "replay", app=pi_loop_app("lost_garbled"))


def test_timing_records_said_lost_where_timing_csv_shows_no_place_for_them_are_named(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    run = _run(tmp_path, "lost_nowhere")
    _lose(run, timing_records={"plant": 1})  # every cycle in timing.csv, to the run's end: where was it lost?
    result = replay(run, tmp_path / "replay", app=pi_loop_app("lost_nowhere"))
    assert not result.equal and result.cannot is None
    assert result.lost == ("the run says it lost 1 of plant's timing records (recording.lost), yet timing.csv shows "
                           "no place they could have been: the replay cannot tell what they were",)


def test_a_recording_stopped_by_a_full_disk_replays_what_it_holds_and_says_where_it_stopped(tmp_path: Path) -> None:
    from rtloop.runtime.replay import replay

    run = _run(tmp_path, "lost_enospc")
    _lose(run, stopped="recording stopped at 0.1 s of run time: ENOSPC No space left on device; the run went on")
    header, *rows = _rows(run / "timing.csv")
    _write_rows(run / "timing.csv", [header, *sorted(rows, key=lambda row: int(row[2]))])  # as a run drains them
    timing = (run / "timing.csv").read_text()
    cut_at = timing.index("controller,120,")
    (run / "timing.csv").write_text(timing[:cut_at + 20])  # the writer stopped in the middle of a line
    signals = (run / "signals.csv").read_text()
    (run / "signals.csv").write_text(signals[:signals.index("\n0.15,") + 9])
    result = replay(run, tmp_path / "replay", app=pi_loop_app("lost_enospc"))
    assert result.cannot is None and result.divergence is None, result
    assert not result.equal  # the rest of the run was never compared
    assert f"timing.csv line {timing[:cut_at].count(chr(10)) + 1}: its last line is cut short" in "\n".join(result.lost)
    assert "signals.csv line 152: its last line is cut short" in "\n".join(result.lost)
    assert "ENOSPC" in result.lost[0] and "holds every task up to t = " in result.lost[0]
    assert 100 <= result.rows_compared == result.rows_in_run < 151


def test_a_run_killed_during_keep_is_said_to_have_never_finished(tmp_path: Path) -> None:
    from rtloop.errors import AppError
    from rtloop.runtime.replay import replay

    run = _run(tmp_path, "lost_killed", 0.02)
    (run / "timing.csv").unlink()
    (run / "segments").mkdir()  # what a kill -9 of the supervisor during --keep leaves
    with pytest.raises(AppError, match=r"the run never finished \(killed, or still running\): its recording is in "
                                       r"segments/"):
        replay(run, tmp_path / "replay", app=pi_loop_app("lost_killed"))
    summary = json.loads((run / "summary.json").read_text())
    (run / "summary.json").unlink()  # killed before it wrote one
    with pytest.raises(AppError, match=r"the run never finished \(killed, or still running\)"):
        replay(run, tmp_path / "replay", app=pi_loop_app("lost_killed"))
    (run / "segments").rmdir()
    (run / "summary.json").write_text(json.dumps({**summary, "running": True}))
    with pytest.raises(AppError, match=r"summary\.json still says running"):
        replay(run, tmp_path / "replay", app=pi_loop_app("lost_killed"))
