"""A run holds its folder for its whole life: a second run into it, even with --force, is refused
while the first goes on (it would delete the live run's files and mix its own in); after, it may."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import rtloop
from rtloop.app.appfile import load_app
from rtloop.runtime.session import RunDirectoryError

DCMOTOR = Path(__file__).resolve().parents[1] / "examples" / "dcmotor" / "dcmotor.toml"


def _app_file(tmp_path: Path, name: str) -> Path:
    """The DC motor example with a name of its own, in a folder of the test's (its module beside it)."""
    folder = tmp_path / "app"
    folder.mkdir()
    shutil.copy(DCMOTOR.parent / "dcmotor.py", folder / "dcmotor.py")
    text = DCMOTOR.read_text().replace('name = "dcmotor"', f'name = "{name}"')
    (folder / "dcmotor.toml").write_text(text.replace('"profiles/', f'"{DCMOTOR.parent}/profiles/'))
    return folder / "dcmotor.toml"


def test_force_into_the_folder_of_a_live_run_is_refused(tmp_path: Path) -> None:
    app_file = _app_file(tmp_path, f"lockfirst_{os.getpid()}")
    out = tmp_path / "out"
    # (a bound, ended by the Ctrl-C below: the run must outlast its start and the simulate's, seconds under load)
    first = subprocess.Popen([sys.executable, "-m", "rtloop", "run", str(app_file), "--duration", "200",
                              "--out", str(out), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not (out / "summary.json").exists():
            assert first.poll() is None and time.monotonic() < deadline, first.communicate()
            time.sleep(0.05)
        again = subprocess.run([sys.executable, "-m", "rtloop", "simulate", str(app_file), "--duration", "0.1",
                                "--out", str(out), "--force"], capture_output=True, text=True, timeout=120)
        assert again.returncode == 2, again.stderr
        assert "is the folder of a run still going" in again.stderr and "Traceback" not in again.stderr
        assert first.poll() is None  # the first run goes on, untouched
    finally:
        first.send_signal(signal.SIGINT)
        _, err = first.communicate(timeout=60)
    assert first.returncode == 0, err
    with pytest.raises(RunDirectoryError, match="already holds a run"):
        rtloop.simulate(load_app(app_file), 0.05, out)  # ended: the usual refusal, and --force may replace it
    rtloop.simulate(load_app(app_file), 0.05, out, force=True)
