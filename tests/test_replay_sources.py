"""A run records what its app was made of (replay.json's ``files``: the app file, the modules it
loaded, its feeds), and ``rtloop replay`` says first when one changed since the run, and puts a
difference down to that change rather than to a model that is not deterministic."""

from __future__ import annotations

import json
import os
from pathlib import Path

import rtloop
from rtloop.app.appfile import load_app
from rtloop.app.sources import file_digest
from rtloop.runtime.replay import replay

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

APP = """name = "{name}"

[tasks.ctl]
runnable = "gain_module:Gain"
period_ns = 10_000_000

[ports.setpoint]
to = "ctl.u[0]"
feed = "profile.csv"

[record]
signals = ["ctl.y"]
"""

MODULE = '''from rtloop import Runnable

from helper_module import FACTOR


class Gain(Runnable):
    n_inputs, n_outputs = 1, 1

    def step(self, u, y) -> None:
        y[0] = FACTOR * u[0]
'''


def _app_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "app"
    folder.mkdir(mode=0o755, parents=True)
    name = f"replay_src_{os.getpid()}"
    (folder / "app.toml").write_text(APP.format(name=name))
    (folder / "gain_module.py").write_text(MODULE)
    (folder / "helper_module.py").write_text("FACTOR = 2.0\n")
    (folder / "profile.csv").write_text("t_s,setpoint\n0,1.0\n0.05,3.0\n")
    return folder


def test_a_run_records_its_files_and_replay_names_the_one_that_changed(tmp_path: Path) -> None:
    folder = _app_folder(tmp_path)
    rtloop.simulate(load_app(folder / "app.toml"), 0.1, tmp_path / "run")
    files = json.loads((tmp_path / "run" / "replay.json").read_text())["files"]
    for name in ("app.toml", "gain_module.py", "helper_module.py", "profile.csv"):
        path = str((folder / name).resolve())
        assert files.get(path) == file_digest(path), (name, files)
    same = replay(tmp_path / "run", tmp_path / "same")
    assert same.equal and not any("changed" in note for note in same.notes), same.notes

    (folder / "helper_module.py").write_text("FACTOR = 2.5  # tuned after the run\n")
    changed = replay(tmp_path / "run", tmp_path / "changed")
    helper = str((folder / "helper_module.py").resolve())
    assert any(note.startswith(f"{helper} changed since the run") for note in changed.notes), changed.notes
    assert changed.divergence is not None
    told = changed.divergence.describe()
    assert "helper_module.py changed since the run" in told and "may well come from that change" in told, told
    assert "not deterministic" not in told


def test_a_change_that_alters_nothing_is_still_said(tmp_path: Path) -> None:
    folder = _app_folder(tmp_path)
    rtloop.simulate(load_app(folder / "app.toml"), 0.1, tmp_path / "run")
    (folder / "profile.csv").write_text("t_s,setpoint\n0,1.0\n0.05,3.0\n0.5,4.0\n")  # a row past the run's end
    result = replay(tmp_path / "run", tmp_path / "replay")
    assert result.divergence is None
    assert any("profile.csv changed since the run" in note for note in result.notes), result.notes


def test_modules_loaded_by_a_module_count_whether_loaded_now_or_before() -> None:
    """serial_motor.py loads examples/dcmotor/dcmotor.py by file: both are part of the app, the
    first time it is loaded in a process and every time after (from the module's own record)."""
    app_file = EXAMPLES / "dcmotor_serial" / "dcmotor_serial.toml"
    for _ in range(2):
        made_of = load_app(app_file).sources
        assert str(app_file.resolve()) in made_of
        assert str((EXAMPLES / "dcmotor_serial" / "serial_motor.py").resolve()) in made_of
        assert str((EXAMPLES / "dcmotor" / "dcmotor.py").resolve()) in made_of


def test_an_edited_module_is_loaded_anew_in_the_same_process(tmp_path: Path) -> None:
    """A notebook loads the app, edits the controller's helper, loads the app again: the new code
    runs (a task process would load the file as it is now; the old one must not run beside it)."""
    folder = _app_folder(tmp_path)
    rtloop.simulate(load_app(folder / "app.toml"), 0.02, tmp_path / "before")
    (folder / "helper_module.py").write_text("FACTOR = 5.0\n")
    rtloop.simulate(load_app(folder / "app.toml"), 0.02, tmp_path / "after")
    before = (tmp_path / "before" / "signals.csv").read_text().splitlines()[-1].split(",")
    after = (tmp_path / "after" / "signals.csv").read_text().splitlines()[-1].split(",")
    assert float(before[-1]) == 2.0 and float(after[-1]) == 5.0, (before, after)


def test_two_apps_with_a_helper_of_the_same_name_each_get_their_own(tmp_path: Path) -> None:
    """Two students' folders in one notebook, each with helper_module.py: each app's module imports
    its own neighbour, whichever app was loaded first."""
    first, second = _app_folder(tmp_path / "a"), _app_folder(tmp_path / "b")
    (second / "helper_module.py").write_text("FACTOR = 7.0\n")
    results = []
    for index, folder in enumerate((first, second, first)):
        rtloop.simulate(load_app(folder / "app.toml"), 0.02, tmp_path / f"out{index}")
        results.append(float((tmp_path / f"out{index}" / "signals.csv").read_text().splitlines()[-1].split(",")[-1]))
    assert results == [2.0, 7.0, 2.0]
