"""The run summary in words: what a profile delivered, a step slower than its period in one
plain sentence (run and simulate), and the execution-time column of the console table."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest

import rtloop
from conftest import unique_name
from rtloop import App, Runnable
from rtloop.app.appfile import load_app
from rtloop.cli.run import format_summary

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "dcmotor" / "dcmotor.toml"


class SlowStep(Runnable):
    """Takes about 2 ms per step."""

    n_inputs, n_outputs = 0, 1

    def step(self, u, y) -> None:
        time.sleep(0.002)
        y[0] += 1.0


class FastStep(Runnable):
    n_inputs, n_outputs = 0, 1

    def step(self, u, y) -> None:
        y[0] += 1.0


def test_a_fed_port_says_what_its_profile_delivered(tmp_path: Path) -> None:
    summary = rtloop.simulate(load_app(EXAMPLE), 1.5, tmp_path / "sim")
    feed = json.loads((tmp_path / "sim" / "summary.json").read_text())["ports"]["setpoint"]["feed"]
    assert feed["rows"] == 5 and feed["rows_delivered"] == 4 and feed["nudge"] is None  # rows at 0, .1, .6, 1.2 s
    assert feed["file"].endswith("speed_steps.csv")
    text = format_summary(summary, tmp_path / "sim")
    assert "port setpoint (in, pi.u[1]): fed from speed_steps.csv: 4 of 5 rows delivered, each held until the next" \
        in text
    assert "port load (in, plant.u[1]): sent 0, received 0, dropped 0" in text  # a live port as before
    assert "exec µs p50/max" in text.splitlines()[1]


def test_simulate_says_when_a_step_is_slower_than_its_period_on_this_host(tmp_path: Path) -> None:
    app = App("slowsim")
    app.add_task("slow", SlowStep(), period_ns=1_000_000)
    summary = rtloop.simulate(app, 0.05, tmp_path / "sim")
    notes = [note for note in summary.notes if note.startswith("slow's step")]
    assert len(notes) == 1
    assert re.fullmatch(r"slow's step takes about \d+\.\d ms on this host \(mean, simulated\); its period is 1 ms; "
                        r"in real time it would overrun", notes[0]), notes[0]
    assert notes == [n for n in json.loads((tmp_path / "sim" / "summary.json").read_text())["notes"]
                     if n.startswith("slow's")]
    assert f"note: {notes[0]}" in format_summary(summary, tmp_path / "sim")


def test_a_fast_step_gets_no_such_note(tmp_path: Path) -> None:
    app = App("fastsim")
    app.add_task("fast", FastStep(), period_ns=10_000_000)
    summary = rtloop.simulate(app, 0.05, tmp_path / "sim")
    assert not [note for note in summary.notes if "step takes" in note]


@pytest.mark.rt
def test_a_run_says_when_a_step_is_slower_than_its_period(tmp_path: Path) -> None:
    app = App(unique_name("slowrun"))
    app.add_task("slow", SlowStep(), period_ns=1_000_000, priority=10)
    summary = rtloop.run(app, 0.3, tmp_path / "run")
    notes = [note for note in summary.notes if note.startswith("slow's step")]
    assert len(notes) == 1 and re.fullmatch(r"slow's step takes about \d+\.\d ms \(p50\); its period is 1 ms",
                                            notes[0]), summary.notes
    assert notes[0] in json.loads((tmp_path / "run" / "summary.json").read_text())["notes"]
    text = format_summary(summary, tmp_path / "run")
    row = next(line for line in text.splitlines() if line.startswith("slow "))
    exec_p50_us = float(row.split()[5].split("/")[0])
    assert exec_p50_us > 1000.0  # the execution-time column shows the 2 ms step


def _app_file(tmp_path: Path, policy: str) -> Path:
    (tmp_path / "app.toml").write_text(
        f'name = "reqrt{policy}"\n[tasks.fast]\nrunnable = "rt_test_runnables:Counter"\nperiod_ns = 1_000_000\n'
        f'policy = "{policy}"\n' + ('priority = 10\n' if policy == "fifo" else ""))
    return tmp_path / "app.toml"


def test_require_rt_refuses_a_task_that_would_not_run_real_time(tmp_path: Path, capsys) -> None:
    from rtloop.cli.main import main

    assert main(["run", str(_app_file(tmp_path, "other")), "--duration", "0.1", "--out", str(tmp_path / "out"),
                 "--require-rt"]) == 2
    assert "--require-rt: task 'fast' has policy = \"other\", which is not real time" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # refused before anything started


def test_require_rt_refuses_a_process_without_real_time_privileges(tmp_path: Path, rtloop_env) -> None:
    import shutil
    import subprocess
    import sys

    if shutil.which("setpriv") is None or shutil.which("prlimit") is None:
        pytest.skip("setpriv and prlimit (util-linux) are needed to drop the privileges")
    command = ["setpriv", "--inh-caps=-all", "--bounding-set=-all", "--", "prlimit", "--rtprio=0", "--",
               sys.executable, "-m", "rtloop.cli", "run", str(_app_file(tmp_path, "fifo")), "--duration", "0.1",
               "--out", str(tmp_path / "out"), "--require-rt"]
    done = subprocess.run(command, env=rtloop_env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert "--require-rt: this process may not use real-time scheduling (no CAP_SYS_NICE and RLIMIT_RTPRIO is 0)" \
        in done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "out").exists()
