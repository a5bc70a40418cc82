"""A profile feed is a bounded regular file: ``/dev/zero`` (memory without end), a FIFO (a start
that waits forever) or a file over the bound are refused in one line naming the port and the
path, exit 2, before anything starts — from the app file and from ``--feed``, in run,
simulate, sweep and replay."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rtloop.app.profiles import MAX_PROFILE_BYTES, load_profile
from rtloop.errors import AppError

TESTS = Path(__file__).resolve().parent
APP = """name = "{name}"
[tasks.echo]
runnable = "rt_test_runnables:Gain"
args = {{ n = 1 }}
period_ns = 1_000_000
[ports.setpoint]
to = "echo.u[0]"
{feed}
"""


def _rtloop(*args: str | Path, timeout_s: float = 60) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "rtloop", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout_s, env=env)


def _app(tmp_path: Path, feed: str | Path | None, tag: str) -> Path:
    app = tmp_path / "app.toml"
    line = f'feed = "{feed}"' if feed is not None else ""
    app.write_text(APP.format(name=f"feedbound_{tag}_{os.getpid()}", feed=line))
    return app


def _bad_feeds(tmp_path: Path) -> dict[str, Path]:
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    huge = tmp_path / "huge.csv"
    with open(huge, "wb") as file:
        file.truncate(MAX_PROFILE_BYTES + 1)  # sparse: takes no disk
    return {"dev_zero": Path("/dev/zero"), "fifo": fifo, "huge": huge, "folder": tmp_path}


def _assert_refused(run: subprocess.CompletedProcess[str], path: Path, out: Path) -> None:
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1, run.stderr
    assert "port 'setpoint'" in lines[0] and str(path) in lines[0], run.stderr
    assert "Traceback" not in run.stderr and not out.exists()


@pytest.mark.parametrize("kind", ["dev_zero", "fifo", "huge", "folder"])
def test_a_feed_in_the_app_file_that_is_not_a_bounded_file_is_refused(tmp_path, kind):
    path = _bad_feeds(tmp_path)[kind]
    app = _app(tmp_path, path, kind)
    out = tmp_path / "out"
    run = _rtloop("simulate", app, "--duration", "0.05", "--out", out)
    _assert_refused(run, path, out)
    message = {"dev_zero": "is not a regular file", "fifo": "is not a regular file", "folder": "is a directory",
               "huge": f"has {MAX_PROFILE_BYTES + 1} bytes; a profile feed has at most {MAX_PROFILE_BYTES}"}[kind]
    assert message in run.stderr


@pytest.mark.parametrize("command", ["run", "simulate", "sweep"])
def test_a_bad_feed_on_the_command_line_is_refused_in_every_command(tmp_path, command):
    paths = _bad_feeds(tmp_path)
    app = _app(tmp_path, None, command)
    out = tmp_path / "out"
    for kind in ("dev_zero", "fifo"):
        extra = ["--param", "echo.gain=1:2:2"] if command == "sweep" else []
        run = _rtloop(command, app, "--duration", "0.05", "--out", out, "--feed", f"setpoint={paths[kind]}", *extra)
        _assert_refused(run, paths[kind], out)


def test_replay_of_a_run_whose_feed_became_a_fifo_is_refused(tmp_path):
    profile = tmp_path / "profile.csv"
    profile.write_text("t_s,value\n0,1.0\n0.01,2.0\n")
    app = _app(tmp_path, profile, "replay")
    run_dir = tmp_path / "run"
    first = _rtloop("simulate", app, "--duration", "0.02", "--out", run_dir)
    assert first.returncode == 0, first.stderr
    profile.unlink()
    os.mkfifo(profile)
    out = tmp_path / "replayed"
    _assert_refused(_rtloop("replay", run_dir, "--out", out), profile, out)


def test_a_file_swapped_for_a_fifo_after_loading_is_not_waited_on(tmp_path):
    fifo = tmp_path / "late.csv"
    os.mkfifo(fifo)
    with pytest.raises(AppError, match=r"late\.csv is not a regular file"):
        load_profile(fifo, 1, "port 'setpoint'")


@pytest.mark.parametrize("text, message", [
    ("t_s,value\n1e300,1.0\n", "t_s is 1e+300; at most 1e+09 s"),
    ("t_s,value\n0,\0\n", "not a number"),
    ("t_s,value\n0," + "1" * 200_000 + "\n", "not CSV"),
    (b"t_s,value\n0,\xff\n", ": not UTF-8 text (byte 12)"),
])
def test_a_malformed_profile_is_one_line_naming_the_file(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(AppError) as refused:
        load_profile(path, 1, "port 'setpoint'")
    assert message in str(refused.value) and str(path) in str(refused.value)


def test_a_profile_reads_as_before(tmp_path):
    path = tmp_path / "ok.csv"
    path.write_text("t_s,a,b\n0,1,2\n\n0.5,3,4\n")
    t_ns, values = load_profile(path, 2, "port 'p'")
    assert t_ns.tolist() == [0, 500_000_000]
    assert np.array_equal(values, [[1.0, 2.0], [3.0, 4.0]])
