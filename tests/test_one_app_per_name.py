"""One live app per name and user (B8): ``rtloop port write NAME`` must never pick one of two apps
in silence. A second ``rtloop run`` of a name that a live app of the same user holds is refused;
a registry whose supervisor is gone holds nothing; and if two registries of one name ever exist
(a race, an older rtloop), ``port`` refuses the name instead of choosing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name, wait_for_app
from rt_test_runnables import Counter
from rtloop.ipc.ports import AppNotReachable, connect_app
from rtloop.ipc.segments import SHM_DIR, new_run_token


def _app_file(folder: Path, name: str) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(f'name = "{name}"\n[tasks.t]\nrunnable = "rt_test_runnables:Noop"\n'
                    'period_ns = 1_000_000\npolicy = "other"\n')
    return path


def _rtloop(args: list[str], env: dict[str, str], **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "rtloop.cli", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kwargs)


def test_a_second_run_of_a_live_name_is_refused(tmp_path: Path, rtloop_env: dict[str, str]) -> None:
    name = unique_name("twice")
    app_file = _app_file(tmp_path, name)
    # (a bound, ended by the test: the first must outlast its own start and the second's, seconds each under load)
    first = _rtloop(["run", str(app_file), "--duration", "200", "--out", str(tmp_path / "first"), "-q"], rtloop_env)
    try:
        wait_for_app(name, first)
        second = _rtloop(["run", str(app_file), "--duration", "60", "--out", str(tmp_path / "second"), "-q"],
                         rtloop_env)
        _, stderr = second.communicate(timeout=120)
        assert second.returncode == 2, stderr
        assert len(stderr.strip().splitlines()) == 1, stderr
        assert f"app {name!r} is already running (pid {first.pid})" in stderr
        assert not (tmp_path / "second").exists()  # refused before anything was written
        assert first.poll() is None and connect_app(name).pid == first.pid
    finally:
        first.terminate()
        first.communicate(timeout=60)


def _registry(name: str, pid: int) -> Path:
    path = SHM_DIR / f"rtloop-{name}-{pid}-{new_run_token()}-registry.json"
    fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    with os.fdopen(fd, "w") as file:
        json.dump({"app": name, "pid": pid, "mode": "run", "ports": {}, "tasks": {}}, file)
    return path


def test_a_registry_whose_supervisor_is_gone_holds_nothing(tmp_path: Path) -> None:
    name = unique_name("deadreg")
    ended = subprocess.Popen(["true"])
    ended.wait()
    dead = _registry(name, ended.pid)
    try:
        app = rtloop.App(name)
        app.add_task("count", Counter(), period_ns=1_000_000, policy="other")
        rtloop.run(app, duration_s=0.05, out=tmp_path / "out")
        assert (tmp_path / "out" / "summary.json").exists()
    finally:
        dead.unlink(missing_ok=True)


def test_a_name_two_live_registries_claim_is_refused_not_guessed() -> None:
    name = unique_name("ambig")
    sleepers = [subprocess.Popen(["sleep", "60"]) for _ in range(2)]
    registries = [_registry(name, sleeper.pid) for sleeper in sleepers]
    try:
        with pytest.raises(AppNotReachable, match=rf"{name}.*{sleepers[0].pid}.*{sleepers[1].pid}|"
                                                  rf"{name}.*{sleepers[1].pid}.*{sleepers[0].pid}"):
            connect_app(name)
    finally:
        for sleeper in sleepers:
            sleeper.kill()
            sleeper.wait()
        for path in registries:
            path.unlink(missing_ok=True)


def test_simulations_of_one_name_may_run_side_by_side(tmp_path: Path) -> None:
    name = unique_name("simtwice")
    sleeper = subprocess.Popen(["sleep", "60"])
    path = SHM_DIR / f"rtloop-{name}-{sleeper.pid}-{new_run_token()}-registry.json"
    path.write_text(json.dumps({"app": name, "pid": sleeper.pid, "mode": "simulate", "ports": {}, "tasks": {}}))
    path.chmod(0o600)
    try:  # a sweep simulates one app in several processes at once
        app = rtloop.App(name)
        app.add_task("count", Counter(), period_ns=1_000_000, policy="other")
        rtloop.simulate(app, 0.05, tmp_path / "out")
    finally:
        sleeper.kill()
        sleeper.wait()
        path.unlink(missing_ok=True)

