"""A run directory is never overwritten unless asked: run, simulate, replay, Python and CLI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import rtloop
from rt_test_runnables import Counter
from rtloop import App
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
    app = App(name)
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
