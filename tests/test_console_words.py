"""What the console says, in a few words that were wrong: rtloop's own device fault without rtloop's
traceback under it (summary.json keeps it, --debug prints it), '–' for the timing of a run that
never reached its first cycle, and a live view served beyond this machine said to be."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

from conftest import unique_name
from rtloop.cli.run import _us
from rtloop.errors import TaskFailed
from rtloop.record.foxglove_live import served_to

TESTS = Path(__file__).resolve().parent
APP = """name = "{name}"
[tasks.ctl]
runnable = "device_test_drivers:Echo"
args = {{ nan_at = 3 }}
period_ns = 2_000_000
priority = 10
[devices.dev]
kind = "device_test_drivers:LogDevice"
task = "ctl"
log = "{log}"
twin = "device_test_drivers:MirrorTwin"
[devices.dev.limits.c0]
min = -10.0
max = 10.0
safe = 0.0
[[connect]]
from = "ctl.y[0]"
to = "dev.u[0]"
[[connect]]
from = "dev.y[0]"
to = "ctl.u[0]"
"""


def _simulate(tmp_path: Path, *debug: str) -> subprocess.CompletedProcess[str]:
    app = tmp_path / "app.toml"
    app.write_text(APP.format(name=unique_name("words"), log=tmp_path / "dev.log"))
    env = {"PYTHONPATH": str(TESTS), "PATH": "/usr/bin:/bin"}
    return subprocess.run([sys.executable, "-m", "rtloop", *debug, "simulate", str(app), "--duration", "0.1",
                           "--out", str(tmp_path / "out"), "--force"], capture_output=True, text=True, timeout=120,
                          env=env)


def test_rtloops_own_device_fault_is_said_without_its_traceback(tmp_path: Path) -> None:
    done = _simulate(tmp_path)
    assert done.returncode == 1, done.stderr
    assert "dev.u[0] (c0): command nan is not finite" in done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    failure = json.loads((tmp_path / "out" / "summary.json").read_text())["failure"]
    assert "Traceback" in failure["traceback"]  # kept where a driver's author looks
    assert "Traceback" in _simulate(tmp_path, "--debug").stderr


def test_a_runnables_own_exception_keeps_its_traceback() -> None:
    raised = TaskFailed("t", 3, "step", "ZeroDivisionError: division by zero", "Traceback ...")
    own = TaskFailed("t", 3, "step", "DeviceFault: task 't', cycle 3: dev.u[0] (c0): command nan is not finite",
                     "Traceback ...")
    assert not raised.said_in_full and own.said_in_full


def test_no_cycle_is_a_dash_not_nan() -> None:
    assert _us(math.nan) == "–" and _us(12_345.0) == "12.3"


def test_a_live_view_on_every_interface_says_who_may_see_and_write() -> None:
    assert served_to("127.0.0.1", ["setpoint"]) == ""
    assert served_to("0.0.0.0", []) == "; it listens on every network interface: anyone on the network who reaches " \
                                       "it sees the signals"
    assert served_to("192.168.1.5", ["setpoint", "gains"]).endswith("sees the signals and may write ports setpoint, "
                                                                     "gains")


def test_the_watchdog_names_a_stopped_process_as_stopped() -> None:
    import signal
    import time

    from rtloop.linux.hygiene import why_stuck as _why_stuck

    sleeper = subprocess.Popen(["sleep", "30"])
    try:
        assert _why_stuck(sleeper.pid) == "the step is stuck (a blocking call or an endless loop)"
        sleeper.send_signal(signal.SIGSTOP)
        deadline = time.monotonic() + 10
        while "stopped" not in _why_stuck(sleeper.pid) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert _why_stuck(sleeper.pid).startswith("its process is stopped (state T: SIGSTOP")
    finally:
        sleeper.kill()
        sleeper.wait()


def test_sweep_help_says_how_its_runs_are_numbered(capsys) -> None:
    import pytest

    from rtloop.cli.main import main

    with pytest.raises(SystemExit):
        main(["sweep", "--help"])
    assert "numbered from 0, as wide as the count needs" in " ".join(capsys.readouterr().out.split())


def test_port_read_heads_its_columns_with_names_signals_and_units() -> None:
    from rtloop.cli.port import column_names

    info = {"signal": "plant.y[0:2]", "names": ["speed_rad_s", ""], "units": ["rad/s", ""]}
    assert column_names(info) == ["speed_rad_s (plant.y[0]) [rad/s]", "plant.y[1]"]
    assert column_names({"signal": "pi.u[1]", "names": "not a list"}) == ["pi.u[1]"]
