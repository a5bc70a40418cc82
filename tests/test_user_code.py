"""User code reaches its task processes: modules beside the app file import each other, a
Runnable defined in ``__main__`` (script, notebook, ``python -``) travels by value, and a
failure while loading a task's class says "loading", not "prerun"."""

from __future__ import annotations

import json
import os
import secrets
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

import rtloop
from rtloop.app.appfile import load_app
from rtloop.app.byvalue import RunnableNotSendable, dumps_runnable, loads_runnable
from rtloop.errors import AppFileError, TaskFailed

ROOT = os.geteuid() == 0


def _app_toml(folder: Path, name: str, runnable: str) -> Path:
    path = folder / "app.toml"
    path.write_text(f'name = "{name}"\n[tasks.t]\nrunnable = "{runnable}"\nperiod_ns = 1_000_000\npriority = 10\n'
                    '[record]\nsignals = ["t.y"]\n')
    return path


def _two_modules(folder: Path, tag: str) -> tuple[str, str]:
    motor, faulty = f"motor_{tag}", f"faulty_{tag}"
    (folder / f"{motor}.py").write_text(textwrap.dedent("""
        from rtloop import Runnable

        class PiSpeed(Runnable):
            n_inputs, n_outputs = 0, 1

            def step(self, u, y):
                y[0] = 7.0
    """))
    (folder / f"{faulty}.py").write_text(f"import json\nfrom {motor} import PiSpeed\n\n"
                                         "class Faulty(PiSpeed):\n    json_dumps = json.dumps\n")
    (folder / "json.py").write_text("raise SystemExit('the folder shadowed the json module')\n")
    return motor, faulty


def test_modules_beside_the_app_file_import_each_other_in_the_task_process(tmp_path: Path) -> None:
    _, faulty = _two_modules(tmp_path, secrets.token_hex(3))
    app = load_app(_app_toml(tmp_path, f"sib{os.getpid()}", f"{faulty}:Faulty"))
    assert type(app.tasks["t"].runnable).json_dumps is json.dumps  # the standard json, not json.py beside it
    assert str(tmp_path) not in sys.path
    rtloop.run(app, duration_s=0.05, out=tmp_path / "out")
    lines = (tmp_path / "out" / "signals.csv").read_text().splitlines()
    assert lines[2].split(",")[1] == "7.0"  # the task process ran Faulty, whose base came from the sibling


def test_a_sibling_owned_by_someone_else_is_refused(tmp_path: Path) -> None:
    if not ROOT:
        pytest.skip("needs root to give a file to another owner")
    motor, faulty = _two_modules(tmp_path, secrets.token_hex(3))
    os.chown(tmp_path / f"{motor}.py", 65534, 65534)
    with pytest.raises(AppFileError, match="is owned by uid 65534, not by you"):
        load_app(_app_toml(tmp_path, "sibown", f"{faulty}:Faulty"))


def test_a_class_that_fails_to_load_in_the_task_process_is_reported_as_loading(tmp_path: Path) -> None:
    module = f"onlyhere_{secrets.token_hex(3)}"
    (tmp_path / f"{module}.py").write_text(textwrap.dedent("""
        import multiprocessing
        from rtloop import Runnable

        if multiprocessing.parent_process() is not None:
            raise ImportError("this module refuses to load in a task process")

        class Here(Runnable):
            n_inputs, n_outputs = 0, 1

            def step(self, u, y):
                y[0] = 1.0
    """))
    app = load_app(_app_toml(tmp_path, f"load{os.getpid()}", f"{module}:Here"))
    with pytest.raises(TaskFailed) as caught:
        rtloop.run(app, duration_s=0.05, out=tmp_path / "out")
    assert caught.value.phase == "loading"
    assert "refuses to load in a task process" in caught.value.reason


SCRIPT = textwrap.dedent("""
    import rtloop
    from rtloop import App, Runnable

    OFFSET = 3.0

    def offset(x):
        return OFFSET + x

    class Base(Runnable):
        n_inputs, n_outputs = 1, 1

    class Counter(Base):
        parameters = {"k": 2.0}

        def __init__(self):
            super().__init__()
            self.count = 0

        @staticmethod
        def double(x):
            return 2 * x

        def step(self, u, y):
            self.count += 1
            y[0] = offset(self.double(self.k)) + self.count

    app = App("NAME")
    task = app.add_task("counter", Counter(), period_ns=1_000_000, priority=10)
    app.record(task.y)
    rtloop.run(app, duration_s=0.05, out=OUT)
    print("done")
""")


@pytest.mark.parametrize("how", ["stdin", "script without a main guard"])
def test_a_runnable_defined_in_main_travels_by_value(tmp_path: Path, how: str) -> None:
    out = tmp_path / "out"
    code = SCRIPT.replace("NAME", f"main{os.getpid()}{len(how)}").replace("OUT", repr(str(out)))
    if how == "stdin":
        done = subprocess.run([sys.executable, "-"], input=code, capture_output=True, text=True, cwd=tmp_path,
                              timeout=120)
    else:
        (tmp_path / "script.py").write_text(code)
        done = subprocess.run([sys.executable, "script.py"], capture_output=True, text=True, cwd=tmp_path,
                              timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.count("done") == 1  # the task process did not run the script again
    values = [float(row.split(",")[1]) for row in (out / "signals.csv").read_text().splitlines()[1:]]
    assert values[0] == 0.0 and len(values) >= 2  # the initial output, then one row per step taken
    assert values[1:] == [8.0 + i for i in range(len(values) - 1)]  # 3 + 2·2 + count


def test_a_runnable_that_cannot_be_sent_says_what_to_do() -> None:
    class HoldsALock(rtloop.Runnable):
        n_inputs, n_outputs = 0, 1

        def __init__(self) -> None:
            self.lock = threading.Lock()

        def step(self, u, y) -> None:
            y[0] = 1.0

    with pytest.raises(RunnableNotSendable) as caught:
        dumps_runnable(HoldsALock(), "t")
    message = str(caught.value)
    assert "\n" not in message and "task 't': HoldsALock cannot be sent" in message and "in prerun" in message


def test_a_local_class_round_trips_with_its_closure_and_parameters() -> None:
    scale = 5.0

    class Local(rtloop.Runnable):
        n_inputs, n_outputs = 1, 1
        parameters = {"k": 1.5}  # noqa: RUF012

        def step(self, u, y) -> None:
            y[0] = scale * self.k * u[0]

    original = Local()
    original.k = 2.0
    copy = loads_runnable(dumps_runnable(original, "t"))
    assert type(copy) is not Local and type(copy).__name__ == "Local"
    assert copy.k == 2.0 and type(copy).parameters == {"k": 1.5}
    import numpy as np

    y = np.zeros(1)
    copy.step(np.ones(1), y)
    assert y[0] == 10.0


def test_a_sibling_that_links_to_a_module_elsewhere_loads_that_file(tmp_path: Path) -> None:
    elsewhere = tmp_path / "lib"
    elsewhere.mkdir()
    app_folder = tmp_path / "app"
    app_folder.mkdir()
    motor, faulty = _two_modules(elsewhere, secrets.token_hex(3))
    (app_folder / f"{faulty}.py").write_text((elsewhere / f"{faulty}.py").read_text())
    (app_folder / f"{motor}.py").symlink_to(elsewhere / f"{motor}.py")
    app = load_app(_app_toml(app_folder, f"link{os.getpid()}", f"{faulty}:Faulty"))
    assert sys.modules[motor].__file__ == str(elsewhere / f"{motor}.py")
    assert type(app.tasks["t"].runnable).__mro__[1].__name__ == "PiSpeed"


def test_two_apps_with_a_same_named_module_run_each_its_own_in_one_process(tmp_path: Path) -> None:
    """A notebook loads app A (``ctl.py`` beside it), then a variant B in another folder (its own
    ``ctl.py``), then runs A again: A runs A's code, B runs B's (it used to fail to send A's class:
    "it's not the same object as ctl.Const")."""
    name = f"ctl_{secrets.token_hex(3)}"
    apps = {}
    for variant, value in (("a", 1.5), ("b", 2.5)):
        folder = tmp_path / variant
        folder.mkdir()
        (folder / f"{name}.py").write_text(textwrap.dedent(f"""
            from rtloop import Runnable

            class Const(Runnable):
                n_inputs, n_outputs = 0, 1

                def step(self, u, y):
                    y[0] = {value}
        """))
        apps[variant] = load_app(_app_toml(folder, f"twomod{variant}{os.getpid()}", f"{name}:Const"))
    for variant, value in (("a", "1.5"), ("b", "2.5"), ("a", "1.5")):
        out = tmp_path / f"{variant}-{len(list(tmp_path.glob('*-run*')))}-run"
        rtloop.run(apps[variant], duration_s=0.05, out=out)
        assert (out / "signals.csv").read_text().splitlines()[2].split(",")[1] == value, variant
        sim = out.with_name(out.name + "-sim")
        rtloop.simulate(apps[variant], 0.01, sim)
        assert (sim / "signals.csv").read_text().splitlines()[2].split(",")[1] == value, variant
