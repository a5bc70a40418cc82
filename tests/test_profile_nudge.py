"""A port fed from a profile, plus live nudges: ``offset`` adds the latest write to the row in
force, ``override`` lets a write hold until the next row. Same results from the C hot path and
its Python twin, in a simulation and (through the CLI's port writes) in a real-time run."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import rtloop
from rt_test_runnables import Gain  # type: ignore[import-not-found]
from rtloop import App
from rtloop.app.appfile import load_app
from rtloop.errors import AppError, AppFileError
from rtloop.ipc.ports import PortValueError, connect_app

P = 1_000_000
PROFILE = "t_s,value\n0,1.0\n0.010,2.0\n0.020,3.0\n"


def _app(tmp_path: Path, nudge: str | None, name: str = "nudge") -> App:
    (tmp_path / "profile.csv").write_text(PROFILE)
    app = App(name)
    echo = app.add_task("echo", Gain(1, gain=1.0), period_ns=P)
    app.port("setpoint", to=echo.u[0], feed=tmp_path / "profile.csv", nudge=nudge)
    app.record(echo.u)
    return app


def _column(path: Path) -> dict[float, float]:
    with open(path / "signals.csv", newline="") as file:
        return {round(float(row["t_s"]), 6): float(row["echo.u[0]"]) for row in csv.DictReader(file)}


def _u_at_release(signals: dict[float, float], cycle: int) -> float:
    return signals[round(cycle * 0.001, 6)]  # inputs are labelled with the release that read them


@pytest.mark.parametrize("nudge, expected", [
    # cycle:    3     5     9    10    15    20    25
    ("offset", [1.0, 1.5, 1.5, 2.5, 1.75, 2.75, 2.75]),
    ("override", [1.0, 0.5, 0.5, 2.0, -0.25, 3.0, 3.0]),
])
def test_live_writes_combine_with_the_profile(tmp_path: Path, hot_path: str, nudge: str,
                                              expected: list[float]) -> None:
    writes = {("echo", 5): [("setpoint", [0.5])], ("echo", 15): [("setpoint", [-0.25])]}
    rtloop.simulate(_app(tmp_path, nudge), 0.03, tmp_path / "out", port_writes=writes)
    signals = _column(tmp_path / "out")
    assert [_u_at_release(signals, k) for k in (3, 5, 9, 10, 15, 20, 25)] == expected


def test_without_nudge_a_fed_port_follows_its_profile_and_holds_each_row(tmp_path: Path, hot_path: str) -> None:
    rtloop.simulate(_app(tmp_path, None), 0.03, tmp_path / "out")
    signals = _column(tmp_path / "out")
    assert [_u_at_release(signals, k) for k in (0, 9, 10, 19, 20, 29)] == [1.0, 1.0, 2.0, 2.0, 3.0, 3.0]


def test_nudge_needs_a_profile_and_a_known_mode(tmp_path: Path) -> None:
    app = App("nudge_bad")
    echo = app.add_task("echo", Gain(1, gain=1.0), period_ns=P)
    with pytest.raises(AppError, match=r"nudge 'add'; expected one of \['offset', 'override'\]"):
        app.port("x", to=echo.u[0], nudge="add")
    app.port("setpoint", to=echo.u[0], nudge="offset")
    with pytest.raises(AppError, match="no profile feeds it"):
        app.validate()


def test_the_app_file_takes_nudge_and_range_or_value_range(tmp_path: Path) -> None:
    (tmp_path / "profile.csv").write_text(PROFILE)
    text = ('name = "nudgefile"\n[tasks.echo]\nrunnable = "rt_test_runnables:Gain"\nargs = { n = 1 }\n'
            'period_ns = 1_000_000\n[ports.setpoint]\nto = "echo.u[0]"\nfeed = "profile.csv"\n'
            'nudge = "offset"\nKEY = [-1.0, 1.0]\n')
    for key in ("range", "value_range"):
        (tmp_path / "app.toml").write_text(text.replace("KEY", key))
        port = load_app(tmp_path / "app.toml").ports["setpoint"]
        assert port.nudge == "offset" and port.value_range == (-1.0, 1.0)
    (tmp_path / "app.toml").write_text(text.replace("KEY", "range = [0.0, 1.0]\nvalue_range"))
    with pytest.raises(AppFileError, match="give range or value_range"):
        load_app(tmp_path / "app.toml")


@pytest.mark.rt
def test_a_real_time_run_takes_an_offset_written_while_it_runs(tmp_path: Path, rtloop_env: dict[str, str]) -> None:
    name = f"nudgert{os.getpid()}"
    (tmp_path / "profile.csv").write_text("t_s,value\n0,1.0\n")
    (tmp_path / "app.toml").write_text(
        f'name = "{name}"\n[tasks.echo]\nrunnable = "rt_test_runnables:Gain"\nargs = {{ n = 1 }}\n'
        'period_ns = 1_000_000\npriority = 10\n[ports.setpoint]\nto = "echo.u[0]"\nfeed = "profile.csv"\n'
        'nudge = "offset"\nrange = [-1.0, 1.0]\n[ports.echoed]\nsource = "echo.y"\n[record]\nsignals = ["echo.u"]\n')
    # Until Ctrl-C, once the loop has echoed the nudged value (the duration is only a bound)
    command = [sys.executable, "-m", "rtloop.cli", "run", str(tmp_path / "app.toml"), "--duration", "200",
               "--out", str(tmp_path / "out"), "-q"]
    process = subprocess.Popen(command, env=rtloop_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        app = connect_app(name, timeout_s=60)
        with app.reader("echoed") as echoed:  # the loop runs and reads the profile alone
            deadline = time.monotonic() + 30
            while not len(echoed.read()[0]) and time.monotonic() < deadline:
                time.sleep(0.05)
            with pytest.raises(PortValueError, match="outside its range"):
                app.write("setpoint", [2.0])
            app.write("setpoint", [0.5])
            deadline = time.monotonic() + 30
            while 1.5 not in echoed.read()[1] and time.monotonic() < deadline:
                time.sleep(0.05)
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 0, stderr
    values = set(_column(tmp_path / "out").values())
    assert {1.0, 1.5} <= values <= {0.0, 1.0, 1.5}  # the profile, then the profile + 0.5
