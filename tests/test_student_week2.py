"""Issue 30, a student's second week: the library's own warning without real time (6), one word and
one count per kind of stale read (7), and the smaller ones (10), each with the case that showed it."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import rtloop
from conftest import unique_name
from device_test_drivers import Echo, MirrorTwin
from rtloop import App
from rtloop.errors import AppError, TaskFailed
from rtloop.models.base import StepSizeWarning
from rtloop.models.python import PythonModel
from rtloop.record.load import Signals
from rtloop.record.summary import stale_device_notes

MS = 1_000_000
LIMIT = {"min": -1e6, "max": 1e6, "safe": -7.0}
ROOT = Path(__file__).resolve().parents[1]


# --- 6: rtloop.run without privileges says so, in Python ------------------------------------------
@pytest.mark.skipif(shutil.which("setpriv") is None or shutil.which("prlimit") is None,
                    reason="setpriv and prlimit (util-linux) are needed to drop the privileges")
def test_rtloop_run_without_privileges_warns_and_notes_it(tmp_path: Path, rtloop_env: dict[str, str]) -> None:
    script = (
        "import json, sys, warnings\n"
        "import rtloop\n"
        "from rt_test_runnables import Counter\n"
        f"app = rtloop.App({unique_name('unprivileged_py')!r})\n"
        "app.add_task('counter', Counter(), period_ns=1_000_000, priority=70)\n"
        "app.add_task('chosen', Counter(), period_ns=1_000_000, policy='other')\n"
        "with warnings.catch_warnings(record=True) as caught:\n"
        "    warnings.simplefilter('always')\n"
        "    summary = rtloop.run(app, 0.2, sys.argv[1])\n"
        "print(json.dumps([[w.category.__name__, str(w.message), w.filename] for w in caught]))\n"
    )
    command = ["setpriv", "--inh-caps=-all", "--bounding-set=-all", "--", "prlimit", "--rtprio=0", "--",
               sys.executable, "-c", script, str(tmp_path / "out")]
    done = subprocess.run(command, env=rtloop_env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    caught = json.loads(done.stdout.strip().splitlines()[-1])
    said = [message for category, message, _ in caught if category == "NotRealTimeWarning"]
    assert len(said) == 1 and said[0].startswith("task 'counter' asked for fifo but did NOT run real-time (other)")
    assert "Operation not permitted" in said[0]
    assert [filename for category, _, filename in caught if category == "NotRealTimeWarning"] == ["<string>"]
    notes = json.loads((tmp_path / "out" / "summary.json").read_text())["notes"]
    assert said[0] in notes  # the summary says it too; 'chosen' asked for other and got it: nothing to say


# --- 7: stale reads, one vocabulary -----------------------------------------------------------------
def test_connection_and_device_stale_reads_have_a_name_and_a_count_each_everywhere(tmp_path: Path) -> None:
    from rtloop.cli.run import format_summary
    from rtloop.report.data import load_run
    from rtloop.report.html import summary_table

    app = App(unique_name("stale_words"))
    ctl = app.add_task("ctl", Echo(), period_ns=MS, policy="other")
    dev = app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(tmp_path / "dev.log"),
                         twin=MirrorTwin(1), limits={"c0": LIMIT})
    app.connect(ctl.y[0], dev.u[0])
    app.connect(dev.y[0], ctl.u[0])
    summary = rtloop.simulate(app, 0.05, tmp_path / "run")
    device = {"task": "ctl", "kind": "can", "stale_reads": 3, "stale_cycles": 2, "first_stale_cycles": [7, 8],
              "longest_lag_cycles": 1, "stale_reads_by_source": {}}
    summary = dataclasses.replace(summary, devices={"dev": device})
    summary.write(tmp_path / "run" / "summary.json")
    entry = json.loads((tmp_path / "run" / "summary.json").read_text())["tasks"]["ctl"]
    assert (entry["stale_connection_reads"], entry["stale_device_reads"]) == (0, 3)
    assert "stale_reads" not in entry  # the unqualified name meant one kind here, the other in the notes
    table = format_summary(summary, tmp_path / "run").splitlines()
    assert table[1].endswith("stale conn/dev") and table[2].endswith(" 0/3")
    html = summary_table(load_run(tmp_path / "run"))
    assert "<td class=\"name\">stale connection reads</td><td>0</td>" in html
    assert "<td class=\"name\">stale device reads</td><td class=\"bad\">3</td>" in html
    assert stale_device_notes({"dev": device})[0].startswith("device 'dev' (task ctl): 3 stale device reads")


# --- 10: the smaller ones ---------------------------------------------------------------------------
def test_a_nan_command_is_reported_as_the_write_at_the_release_not_the_step(tmp_path: Path) -> None:
    app = App(unique_name("nan_release"))
    ctl = app.add_task("ctl", Echo(nan_at=4), period_ns=2 * MS)
    dev = app.add_device("dev", "device_test_drivers:LogDevice", task="ctl", log=str(tmp_path / "dev.log"),
                         twin=MirrorTwin(1), limits={"c0": LIMIT})
    app.connect(ctl.y[0], dev.u[0])
    app.connect(dev.y[0], ctl.u[0])
    for how in (rtloop.simulate, rtloop.run):
        with pytest.raises(TaskFailed) as caught:
            how(app, 1.0, tmp_path / how.__name__)
        failed = caught.value
        assert failed.phase == "release" and failed.cycle is not None, how
        assert str(failed).startswith("task 'ctl' failed in the devices' write and read at the release, before "
                                      f"the step, at cycle {failed.cycle}: DeviceFault"), how
        assert f"computed by the step of cycle {failed.cycle - 1}, due at this release" in str(failed)
        failure = json.loads((tmp_path / how.__name__ / "summary.json").read_text())["failure"]
        assert failure["phase"] == "release"
        assert failed.cycle == 5 or how is rtloop.run  # a run that skipped release 4 met the NaN later


def _failed_summary(tmp_path: Path, traceback_text: str) -> Path:
    from test_report import synthetic_records, write_run

    out = write_run(tmp_path / "failed", {"a": synthetic_records()},
                    failure={"task": "a", "cycle": 2000, "phase": "step", "reason": "ValueError: boom",
                             "traceback": traceback_text})
    summary = json.loads((out / "summary.json").read_text())
    (out / "summary.json").write_text(json.dumps({**summary, "duration_s": 10.0, "elapsed_s": 2.0}))
    return out


TRACEBACK = """Traceback (most recent call last):
  File "/opt/clone/src/rtloop/runtime/task.py", line 98, in run_loop
    runnable.step(u, y)
  File "/home/student/lqr/controller.py", line 31, in step
    y[0] = self.gain / u[1]
           ~~~~~~~~~~^~~~~~
ValueError: boom
"""


def test_a_failed_runs_report_says_how_long_it_ran_and_the_users_line_first(tmp_path: Path) -> None:
    from html import escape

    from rtloop.report.data import load_run
    from rtloop.report.html import banners, machine_table

    run = load_run(_failed_summary(tmp_path, TRACEBACK))
    assert "<td>2.000 of the 10 asked, stopped by fault</td>" in machine_table(run)
    banner = banners(run)
    own = banner.index(escape('File "/home/student/lqr/controller.py", line 31, in step'))
    assert own < banner.index("/opt/clone/src/rtloop/runtime/task.py") and "y[0] = self.gain / u[1]" in banner


LQR_MODULE = """import rtloop


class Lqr(rtloop.Runnable):
    n_inputs, n_outputs = 2, 1
    output_names = ("force_N",)
    input_names = ("theta_rad", "x_m")

    def step(self, u, y):
        y[0] = -u[0]
"""


@pytest.mark.parametrize(("source", "said"), [
    ("lqr.force", r"ports\.force: source: 'lqr\.force' is not a signal \(did you mean 'lqr\.force_N'\?\)"),
    ("lq.y[0]", r"names unknown task 'lq' \(did you mean 'lqr\.y\[0\]'\?\)"),
])
def test_a_wrong_signal_name_gets_a_did_you_mean(tmp_path: Path, source: str, said: str) -> None:
    from rtloop.app.appfile import load_app

    (tmp_path / "lqr.py").write_text(LQR_MODULE)
    app_file = tmp_path / "cart.toml"
    app_file.write_text(f'name = "{unique_name("did_you_mean")}"\n[tasks.lqr]\nrunnable = "lqr:Lqr"\n'
                        f'period_ns = 2_000_000\n[ports.force]\nsource = "{source}"\n')
    with pytest.raises(AppError, match=said):
        load_app(app_file)


def test_the_port_hint_names_paths_that_work_from_where_the_user_is(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    from rtloop.ipc.ports import as_root_command

    monkeypatch.chdir(tmp_path)  # not the clone's top folder
    program, rtloop_command, rest = as_root_command("port").split(" ", 2)
    assert rest in ("port", "-m rtloop port") and os.access(rtloop_command, os.X_OK)
    assert program == str(ROOT / "tools" / "as-root") if (ROOT / "tools" / "as-root").is_file() else "sudo"
    monkeypatch.chdir(ROOT)
    if (ROOT / ".venv" / "bin" / "rtloop").samefile(Path(sys.executable).parent / "rtloop"):
        assert as_root_command("port") == "tools/as-root .venv/bin/rtloop port"


def test_one_deadline_miss_and_one_cycle_in_a_row_are_singular(tmp_path: Path) -> None:
    from rtloop.report.data import load_run
    from rtloop.report.html import criterion
    from test_report import write_run

    cycle = np.arange(1000, dtype=np.int64)
    release = 10**9 + cycle * MS
    end = release + 70_000
    end[500] = release[500] + 3 * MS // 2  # one cycle ends after its deadline
    records = np.stack([cycle, release, release + 20_000, end], axis=1)
    run_dir = write_run(tmp_path / "one_miss", {"a": records})
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["tasks"]["a"]["deadline_misses"] == 1
    assert "1 deadline miss " in criterion(load_run(run_dir), "a")[0] + " "
    note = stale_device_notes({"dev": {"task": "t", "stale_reads": 1, "stale_cycles": 1, "first_stale_cycles": [4],
                                       "longest_lag_cycles": 1}})[0]
    assert "1 stale device read (" in note and " in 1 cycle," in note and "lag 1 cycle in a row" in note


class TwoMsModel(PythonModel):
    n_inputs, n_outputs = 0, 1
    step_size_s = 0.002

    def calculate(self, u, y) -> None:
        y[0] += 1.0


def test_the_step_size_warning_points_at_the_users_line() -> None:
    app = App(unique_name("step_size_py"))
    with pytest.warns(StepSizeWarning) as caught:
        app.add_task("plant", TwoMsModel(), period_ns=MS)  # the line the warning must point at
    assert (caught[0].filename, caught[0].lineno) == (__file__, _line_of("the line the warning must point at"))


def test_the_step_size_warning_of_an_app_file_points_at_its_task(tmp_path: Path) -> None:
    from rtloop.app.appfile import load_app

    (tmp_path / "two_ms.py").write_text("from rtloop.models.python import PythonModel\n\n\n"
                                        "class TwoMs(PythonModel):\n    n_inputs, n_outputs = 0, 1\n"
                                        "    step_size_s = 0.002\n\n    def calculate(self, u, y):\n"
                                        "        y[0] += 1.0\n")
    app_file = tmp_path / "student.toml"
    app_file.write_text(f'name = "{unique_name("step_size_toml")}"\n\n# the plant\n'
                        '[tasks.plant]\nrunnable = "two_ms:TwoMs"\nperiod_ns = 1_000_000\n')
    with pytest.warns(StepSizeWarning) as caught:
        load_app(app_file)
    assert (Path(caught[0].filename).resolve(), caught[0].lineno) == (app_file.resolve(), 4)


def _line_of(text: str) -> int:
    return next(number for number, line in enumerate(Path(__file__).read_text().splitlines(), start=1)
                if text in line and "_line_of" not in line)


def test_the_time_column_by_name_as_by_attribute() -> None:
    t_s = np.array([0.0, 0.001, 0.002])
    signals = Signals(t_s, ("plant.theta_rad",), np.zeros((3, 1)))
    assert signals["t_s"] is signals.t_s
    assert list(signals) == ["plant.theta_rad"]  # a time, not a signal: not among the names
    with pytest.raises(KeyError, match=r"no signal 'plant\.theta'; did you mean 'plant\.theta_rad'\?"):
        signals["plant.theta"]


def test_the_exit_status_of_an_estop_is_documented() -> None:
    devices = (ROOT / "docs" / "devices.md").read_text()
    cli = (ROOT / "docs" / "cli.md").read_text()
    assert "An E-stop edge ends the run with exit status 0" in " ".join(devices.split())
    assert "an E-stop edge (exit 0: a requested stop" in " ".join(cli.split())


def test_warnings_from_elsewhere_are_untouched() -> None:
    """Only a task's own warnings are moved to the user's line; a filter that errors still errors."""
    app = App(unique_name("step_size_error"))
    with warnings.catch_warnings():
        warnings.simplefilter("error", StepSizeWarning)
        with pytest.raises(StepSizeWarning):
            app.add_task("plant", TwoMsModel(), period_ns=MS)
