"""The runs a service keeps (``toolbox/run_history.py``, the unit's ExecStartPre): in a restart
burst the first failure's recording survives the later ones; the history stays bounded."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from rtloop.cli.main import main as cli_main
from rtloop.toolbox.run_history import MAX_RUNS_KEPT, PastRun, past_runs, runs_to_prune, set_aside

JIWY = Path(__file__).resolve().parent.parent / "examples" / "jiwy" / "jiwy.toml"


def _finish(latest: Path, how: str) -> None:
    """A run that recorded into ``latest`` and ended ``how``: a stop reason, or 'crash' (no final summary)."""
    latest.mkdir()
    (latest / "timing.csv").write_text("cycle\n")
    if how == "killed":
        summary = {"running": True, "stopped_by": "running"}  # the progress summary of a run that was killed
    elif how == "crash":
        return
    else:
        summary = {"running": False, "stopped_by": how}
    (latest / "summary.json").write_text(json.dumps(summary))


def _names(state: Path) -> list[str]:
    return sorted(entry.name for entry in state.iterdir())


def test_the_unit_sets_the_last_run_aside_with_run_history_not_rm(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["service", str(JIWY)]) == 0
    unit = capsys.readouterr().out
    pre = [line.partition("=")[2] for line in unit.splitlines() if line.startswith("ExecStartPre=")]
    assert len(pre) == 1, pre
    words = pre[0].split()
    assert Path(words[0]).is_absolute() and Path(words[0]).name.startswith("python")
    assert words[1:] == ["-m", "rtloop.toolbox.run_history", "/var/lib/rtloop/jiwy/latest"]
    assert "rm -rf" not in unit and "previous" not in unit
    assert f"At most {MAX_RUNS_KEPT} are kept" in unit and "first-failure" in unit


def test_the_unit_s_command_runs_and_sets_aside(tmp_path: Path) -> None:
    latest = tmp_path / "latest"
    _finish(latest, "fault")
    done = subprocess.run([sys.executable, "-m", "rtloop.toolbox.run_history", str(latest)], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "kept latest/ as run-0001-first-failure/" in done.stdout
    assert _names(tmp_path) == ["run-0001-first-failure"]


def test_a_restart_burst_keeps_its_first_failure(tmp_path: Path) -> None:
    latest = tmp_path / "latest"
    # a week of clean runs, then a drive that faults at start-up: five restarts, each failing anew
    ends = ["duration", "signal", "signal", "fault", "fault", "crash", "fault", "killed", "fault"]
    for how in ends:
        set_aside(latest, most=4)
        _finish(latest, how)
    set_aside(latest, most=4)  # the unit's next start (after systemctl reset-failed)
    names = _names(tmp_path)
    assert names == ["run-0004-first-failure", "run-0007-failed", "run-0008-failed", "run-0009-failed"], names
    assert json.loads((tmp_path / "run-0004-first-failure" / "summary.json").read_text())["stopped_by"] == "fault"


def test_a_clean_run_between_bursts_makes_the_next_failure_a_first_one(tmp_path: Path) -> None:
    latest = tmp_path / "latest"
    for how in ["fault", "fault", "signal", "watchdog", "fault", "duration"]:
        set_aside(latest)
        _finish(latest, how)
    set_aside(latest)
    assert _names(tmp_path) == ["run-0001-first-failure", "run-0002-failed", "run-0003-clean",
                                "run-0004-first-failure", "run-0005-failed", "run-0006-clean"]


def test_pruning_order_clean_then_later_failures_then_first_failures_never_the_newest_two() -> None:
    def runs(*outcomes: str) -> list[PastRun]:
        return [PastRun(number, outcome, Path(f"run-{number}")) for number, outcome in enumerate(outcomes, 1)]

    history = runs("first-failure", "failed", "clean", "failed", "clean", "first-failure", "clean")
    assert [r.number for r in runs_to_prune(history, most=7)] == []
    assert [r.number for r in runs_to_prune(history, most=5)] == [3, 5]
    assert [r.number for r in runs_to_prune(history, most=3)] == [3, 5, 2, 4]
    assert [r.number for r in runs_to_prune(history, most=2)] == [3, 5, 2, 4, 1]  # 6 and 7: the newest two
    assert [r.number for r in runs_to_prune(runs(*["first-failure"] * 12), most=MAX_RUNS_KEPT)] == [1, 2, 3, 4]


def test_previous_of_the_older_unit_joins_the_history_and_links_are_left_alone(tmp_path: Path) -> None:
    _finish(tmp_path / "previous", "signal")
    _finish(tmp_path / "latest", "fault")
    elsewhere = tmp_path.parent / f"{tmp_path.name}-elsewhere"
    elsewhere.mkdir()
    (tmp_path / "run-0009-clean").symlink_to(elsewhere)  # not a run folder of ours: never moved or removed
    lines = set_aside(tmp_path / "latest", most=2)
    assert lines == ["kept previous/ as run-0001-clean/", "kept latest/ as run-0002-first-failure/"]
    assert _names(tmp_path) == ["run-0001-clean", "run-0002-first-failure", "run-0009-clean"]
    assert elsewhere.is_dir() and [p.path.name for p in past_runs(tmp_path / "latest")] == [
        "run-0001-clean", "run-0002-first-failure"]


def test_a_run_out_of_another_name_gets_its_own_history(tmp_path: Path) -> None:
    out = tmp_path / "robot"
    _finish(out, "duration")
    assert set_aside(out) == ["kept robot/ as robot.run-0001-clean/"]
    os.mkdir(tmp_path / "run-0005-clean")  # another service's history in the same folder: not ours
    assert [p.path.name for p in past_runs(out)] == ["robot.run-0001-clean"]


def test_nothing_to_set_aside_at_the_first_start(tmp_path: Path) -> None:
    assert set_aside(tmp_path / "state" / "latest") == []
