"""A run directory is never overwritten unless asked: run, simulate, replay, Python and CLI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name
from rt_test_runnables import Counter
from rtloop import App
from rtloop.record.summary import SUMMARY_BOUND_BYTES, SUMMARY_RESERVE_BYTES
from rtloop.runtime.session import RunDirectoryError

P = 1_000_000
CLI = [sys.executable, "-m", "rtloop.cli"]
APP_FILE = """name = "{name}"
[tasks.count]
runnable = "rt_test_runnables:Counter"
period_ns = 1_000_000
[record]
signals = ["count.y"]
"""


def counter_app(name: str) -> App:
    app = App(unique_name(name))  # a live app holds its name: this test run's own
    task = app.add_task("count", Counter(), period_ns=P)
    app.record(task.y)
    return app


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes (what must survive a refused run)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def app_file(tmp_path: Path, name: str) -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(APP_FILE.format(name=name))
    return path


def test_simulate_into_a_run_is_refused_and_the_run_is_kept(tmp_path: Path) -> None:
    out = tmp_path / "run"
    rtloop.simulate(counter_app("safety_a"), 0.05, out)
    (out / "report.html").write_text("<html>the first run</html>")
    before = snapshot(out)
    with pytest.raises(RunDirectoryError, match=r"already holds a run.*--force"):
        rtloop.simulate(counter_app("safety_a"), 0.02, out)
    assert snapshot(out) == before


def test_force_replaces_the_run_and_leaves_no_stale_report(tmp_path: Path) -> None:
    out = tmp_path / "run"
    rtloop.simulate(counter_app("safety_b"), 0.05, out)
    (out / "report.html").write_text("<html>the first run</html>")
    (out / "report-figures").mkdir()
    (out / "report-figures" / "a.png").write_bytes(b"png")
    (out / "notes.txt").write_text("mine")  # not a run file: never touched
    summary = rtloop.simulate(counter_app("safety_b"), 0.02, out, force=True)
    assert not (out / "report.html").exists() and not (out / "report-figures").exists()
    assert json.loads((out / "summary.json").read_text())["duration_s"] == 0.02 == summary.duration_s
    assert (out / "notes.txt").read_text() == "mine"


def test_force_removes_the_earlier_runs_kept_code_and_snapshots_too(tmp_path: Path) -> None:
    out = tmp_path / "run"
    rtloop.simulate(counter_app("safety_k"), 0.05, out)
    for folder, name in (("code", "pid-0123456789ab.py"), ("snapshots", "ctl-0.snap")):  # a reload's, a --keep run's
        (out / folder).mkdir()
        (out / folder / name).write_text("the earlier run's")
    rtloop.simulate(counter_app("safety_k"), 0.02, out, force=True)
    assert not (out / "code").exists() and not (out / "snapshots").exists()
    fresh = tmp_path / "fresh"  # code put in for a simulation's reload profile: no run, kept (with --force too)
    (fresh / "code").mkdir(parents=True)
    (fresh / "code" / "pid-0123456789ab.py").write_text("the code to load")
    rtloop.simulate(counter_app("safety_k"), 0.02, fresh, force=True)
    assert (fresh / "code" / "pid-0123456789ab.py").read_text() == "the code to load"


def test_force_removes_a_planted_link_never_what_it_points_to(tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "run"
    out.mkdir()
    (out / "timing.csv").symlink_to(victim)
    with pytest.raises(RunDirectoryError):
        rtloop.simulate(counter_app("safety_c"), 0.02, out)
    rtloop.simulate(counter_app("safety_c"), 0.02, out, force=True)
    assert victim.read_text() == "precious" and not (out / "timing.csv").is_symlink()


def test_a_crashed_runs_segments_are_never_deleted(tmp_path: Path) -> None:
    out = tmp_path / "run"
    (out / "segments").mkdir(parents=True)
    (out / "segments" / "000003-timing.csv").write_text("task,cycle,release_ns,start_ns,end_ns\nx,1,2,3,4\n")
    (out / "summary.json").write_text('{"running": true}\n')
    before = snapshot(out)
    for force in (False, True):
        with pytest.raises(RunDirectoryError, match="did not finish"):
            rtloop.simulate(counter_app("safety_d"), 0.02, out, keep_s=1.0, force=force)
        assert snapshot(out) == before


@pytest.mark.rt
def test_run_into_a_run_is_refused_before_anything_starts(tmp_path: Path) -> None:
    out = tmp_path / "run"
    rtloop.simulate(counter_app("safety_e"), 0.02, out)
    before = snapshot(out)
    with pytest.raises(RunDirectoryError):
        rtloop.run(counter_app("safety_e"), 0.05, out)
    assert snapshot(out) == before
    rtloop.run(counter_app("safety_e"), 0.05, out, force=True)
    assert json.loads((out / "summary.json").read_text())["mode"] == "run"


def test_cli_refuses_in_one_line_with_exit_2(tmp_path: Path, rtloop_env) -> None:
    path = app_file(tmp_path, "safety_cli")
    out = tmp_path / "run"
    first = subprocess.run([*CLI, "simulate", str(path), "--duration", "0.05", "--out", str(out), "-q"],
                           env=rtloop_env, capture_output=True, text=True)
    assert first.returncode == 0, first.stderr
    before = snapshot(out)
    again = subprocess.run([*CLI, "simulate", str(path), "--duration", "0.02", "--out", str(out), "-q"],
                           env=rtloop_env, capture_output=True, text=True)
    assert again.returncode == 2 and len(again.stderr.strip().splitlines()) == 1, again.stderr
    assert "--force" in again.stderr and snapshot(out) == before
    forced = subprocess.run([*CLI, "simulate", str(path), "--duration", "0.02", "--out", str(out), "-q", "--force"],
                            env=rtloop_env, capture_output=True, text=True)
    assert forced.returncode == 0, forced.stderr


@pytest.mark.parametrize("inside", ["", "sub", "sub/deeper", "."])
def test_replay_into_the_run_it_replays_is_refused_before_anything_is_written(
        tmp_path: Path, rtloop_env, inside: str) -> None:
    path = app_file(tmp_path, "safety_replay")
    run_dir = tmp_path / "run"
    made = subprocess.run([*CLI, "simulate", str(path), "--duration", "0.05", "--out", str(run_dir), "-q"],
                          env=rtloop_env, capture_output=True, text=True)
    assert made.returncode == 0, made.stderr
    before = snapshot(run_dir)
    out = run_dir / inside if inside else run_dir
    for force in ([], ["--force"]):
        result = subprocess.run([*CLI, "replay", str(run_dir), "--out", str(out), *force],
                                env=rtloop_env, capture_output=True, text=True)
        assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr
        assert "replays" in result.stderr
        assert snapshot(run_dir) == before
        assert not (run_dir / "sub").exists()
    assert json.loads((run_dir / "summary.json").read_text())["mode"] == "simulate"


def test_replay_through_a_link_to_the_run_is_refused(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    rtloop.simulate(counter_app("safety_link"), 0.02, run_dir)
    before = snapshot(run_dir)
    os.symlink(run_dir, tmp_path / "alias")
    from rtloop.runtime.replay import replay

    with pytest.raises(RunDirectoryError):
        replay(run_dir, tmp_path / "alias", app=counter_app("safety_link"), force=True)
    assert snapshot(run_dir) == before


# --- a disk already full --------------------------------------------------------------------------
@pytest.fixture
def tiny_disk(tmp_path: Path):
    """A 256 KiB tmpfs of this test alone (root only), unmounted at the end."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tiny tmpfs needs root")
    disk = tmp_path / "tiny"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", str(disk)], check=False)


def fill(disk: Path, leave_bytes: int = 0) -> None:
    """Fill ``disk`` up to ``leave_bytes`` free (in whole pages)."""
    stats = os.statvfs(disk)
    free = stats.f_bavail * stats.f_frsize
    with open(disk / f"fill{len(list(disk.iterdir()))}", "wb") as file:
        file.write(b"x" * max(0, free - leave_bytes))


@pytest.mark.parametrize("command", ["simulate", "run"])
def test_a_disk_already_full_is_refused_before_the_run(tiny_disk: Path, tmp_path: Path, rtloop_env,
                                                        command: str) -> None:
    fill(tiny_disk, leave_bytes=16 * 1024)  # room for a few files, not for the summary's reserve
    out = tiny_disk / "run"
    # --keep: the recording's own estimate (test_disk_room.py) would refuse it first without it
    result = subprocess.run([*CLI, command, str(app_file(tmp_path, "safety_full")), "--duration", "0.2",
                             "--keep", "1", "--out", str(out), "-q"], env=rtloop_env, capture_output=True, text=True)
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert f"no space at {out}: 16384 bytes free" in result.stderr
    assert not out.exists()  # no empty summary.json, no temporary left behind


class _PaddedSummary:
    """What SummaryFile.write asks of a summary: ``to_json``, here of a given size."""

    def __init__(self, size: int) -> None:
        self.size = size

    def to_json(self) -> dict[str, str]:
        return {"pad": "x" * self.size}


def test_the_summary_is_never_left_empty_on_a_full_disk(tiny_disk: Path) -> None:
    from rtloop.record.summary import SummaryFile

    out = tiny_disk / "run"
    out.mkdir()
    summary = SummaryFile(out)
    fill(tiny_disk)
    assert summary.write(_PaddedSummary(3000))  # the reserve is given up for it
    assert not (out / ".summary-reserve").exists()
    fill(tiny_disk)
    assert not summary.write(_PaddedSummary(30_000)) and "summary.json not written" in summary.problem
    assert json.loads((out / "summary.json").read_text()) == {"pad": "x" * 3000}  # the previous one, whole
    assert summary.write(_PaddedSummary(2000))  # smaller: over the previous one's own blocks
    assert json.loads((out / "summary.json").read_text()) == {"pad": "x" * 2000}
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]


def test_summaries_growing_to_the_bound_are_still_written_on_a_full_disk(tiny_disk: Path) -> None:
    """The previous summary and its replacement both exist until the rename: the reserve holds both.
    (With a reserve of one summary's worth, a run whose summary had grown past half of it, e.g.
    with 20 misses kept in full on a loaded machine, ended with its last running summary.)"""
    from rtloop.record.summary import SummaryFile

    out = tiny_disk / "run"
    out.mkdir()
    summary = SummaryFile(out)
    assert summary.write(_PaddedSummary(1000))
    fill(tiny_disk)
    for size in (SUMMARY_BOUND_BYTES // 2, SUMMARY_BOUND_BYTES - 8192, SUMMARY_BOUND_BYTES - 100):  # growing
        assert summary.write(_PaddedSummary(size)), (size, summary.problem)
        assert json.loads((out / "summary.json").read_text()) == {"pad": "x" * size}
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]


def test_a_disk_with_room_for_the_reserve_only_runs_and_says_so(tiny_disk: Path, tmp_path: Path,
                                                                 rtloop_env) -> None:
    fill(tiny_disk, leave_bytes=SUMMARY_RESERVE_BYTES)
    out = tiny_disk / "run"
    result = subprocess.run([*CLI, "simulate", str(app_file(tmp_path, "safety_reserve")), "--duration", "0.2",
                             "--out", str(out)], env=rtloop_env, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    listed = next(line for line in result.stdout.splitlines() if line.startswith("artifacts in"))
    assert listed.endswith(": summary.json"), listed  # never an empty timing.csv or run.mcap
    assert "ENOSPC" in json.loads((out / "summary.json").read_text())["recording"]["stopped"]
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no reserve, no temporary
    assert any("ENOSPC" in note for note in rtloop.load(out).notes)


# --- an --out that cannot be a folder ------------------------------------------------------------
@pytest.mark.parametrize("where", ["/proc/rtloop_no_such", "a_file/x"])
def test_an_out_that_cannot_be_made_is_one_line_exit_2(tmp_path: Path, rtloop_env, where: str) -> None:
    (tmp_path / "a_file").write_text("not a folder")
    out = where if where.startswith("/") else str(tmp_path / where)
    result = subprocess.run([*CLI, "simulate", str(app_file(tmp_path, "safety_out")), "--duration", "0.05",
                             "--out", out, "-q"], env=rtloop_env, capture_output=True, text=True)
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "internal error" not in result.stderr, result.stderr
    assert f"--out {out} cannot be used: " in result.stderr


@pytest.mark.skipif(os.geteuid() != 0, reason="becomes another user in a child process: needs root")
def test_an_out_another_user_may_not_write_names_the_path_and_the_reason(tmp_path: Path) -> None:
    from rtloop.runtime.session import prepare_out_dir

    locked = tmp_path / "locked"
    locked.mkdir(mode=0o755)  # root's: nobody may write in it
    tmp_path.chmod(0o755)
    read_end, write_end = os.pipe()
    child = os.fork()
    if child == 0:  # pragma: no cover - the child reports through the pipe
        message = "no refusal"
        try:
            os.setgid(65534)
            os.setuid(65534)
            prepare_out_dir(locked / "run")
        except RunDirectoryError as error:
            message = str(error)
        except BaseException as error:
            message = f"{type(error).__name__}: {error}"
        os.write(write_end, message.encode())
        os._exit(0)
    os.close(write_end)
    os.waitpid(child, 0)
    with os.fdopen(read_end) as pipe:
        message = pipe.read()
    assert message.startswith(f"--out {locked / 'run'} cannot be used: Permission denied"), message
