"""rtloop writes only into folders no other user can plant a link in: an ``--out`` (run, simulate,
replay, sweep, report) owned or writable by another user, or reached through their link, is
refused before anything is written; and the files it makes under names of its own (a temporary
before a rename, the summary's reserve, a figure) are made new, never opened through a link."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from rtloop.newfile import write_new
from rtloop.owners import output_folder_problem

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
DCMOTOR = EXAMPLES / "dcmotor" / "dcmotor.toml"
STRANGER = 54321
"""A uid no test machine gives anyone (no passwd entry needed to own a file)."""

as_root = pytest.mark.skipif(os.geteuid() != 0, reason="needs root to give a folder to another uid")


def _rtloop(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rtloop", *argv], capture_output=True, text=True, timeout=300)


def test_a_planted_link_at_a_temporary_name_is_replaced_not_followed(tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("must survive\n")
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / ".summary.json.tmp").symlink_to(victim)
    write_new(folder / ".summary.json.tmp", b"{}\n")
    assert victim.read_text() == "must survive\n"
    assert not (folder / ".summary.json.tmp").is_symlink() and (folder / ".summary.json.tmp").read_bytes() == b"{}\n"


def test_folders_of_this_user_are_fine_world_writable_ones_are_not(tmp_path: Path) -> None:
    assert output_folder_problem(tmp_path / "new" / "run") is None  # made here: this user's
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    assert "writable by every user" in (output_folder_problem(shared) or "")
    assert "writable by every user" in (output_folder_problem(shared / "run") or "")  # could swap run away
    shared.chmod(0o1777)  # sticky: fine above a run folder (as /tmp is), not as the run folder itself
    assert output_folder_problem(shared / "run") is None
    assert "writable by every user" in (output_folder_problem(shared) or "")


@as_root
def test_another_users_folder_or_link_is_refused_in_one_line_before_anything_runs(tmp_path: Path) -> None:
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    os.chown(theirs, STRANGER, STRANGER)
    result = _rtloop("simulate", str(DCMOTOR), "--duration", "0.05", "--out", str(theirs / "run"))
    assert result.returncode == 2, result.stderr
    assert f"owned by uid {STRANGER}" in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert not (theirs / "run").exists()

    mine = tmp_path / "mine"
    mine.mkdir()
    link = tmp_path / "runs"
    link.symlink_to(mine)
    os.lchown(link, STRANGER, STRANGER)
    result = _rtloop("simulate", str(DCMOTOR), "--duration", "0.05", "--out", str(link / "run"))
    assert result.returncode == 2 and f"symbolic link owned by uid {STRANGER}" in result.stderr, result.stderr
    assert not any(mine.iterdir())


def test_a_report_into_a_folder_others_may_write_is_refused(tmp_path: Path) -> None:
    run = tmp_path / "run"
    assert _rtloop("simulate", str(DCMOTOR), "--duration", "0.05", "--out", str(run)).returncode == 0
    run.chmod(0o777)
    result = _rtloop("report", str(run))
    assert result.returncode == 2 and "writable by every user" in result.stderr, result.stderr
    assert "--out" in result.stderr and not (run / "report.html").exists()
    run.chmod(0o755)
    victim = tmp_path / "elsewhere"
    victim.mkdir()
    (run / "report-figures").symlink_to(victim)  # planted before the folder was locked down
    result = _rtloop("report", str(run))
    assert result.returncode == 0, result.stderr
    assert not any(victim.iterdir()) and (run / "report-figures").is_dir() and not (run / "report-figures").is_symlink()
