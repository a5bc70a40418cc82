"""F-many-tasks: an app has at most MAX_TASKS tasks, and a run refuses task processes that would
lock more memory than the machine can spare; one line, exit 2, nothing started."""

from __future__ import annotations

from pathlib import Path

import pytest

from conftest import unique_name
from rt_test_runnables import Gain
from rtloop.app.appfile import load_app
from rtloop.app.builder import MAX_TASKS, App
from rtloop.cli.main import main
from rtloop.errors import AppError, AppFileError
from rtloop.runtime import layout


def _tasks_file(tmp_path: Path, name: str, count: int, runnable: str) -> Path:
    text = f'name = "{name}"\n' + "".join(
        f'[tasks.t{i}]\nrunnable = "{runnable}"\nargs = {{ n = 1 }}\nperiod_ns = 100_000_000\npolicy = "other"\n'
        for i in range(count))
    path = tmp_path / "many.toml"
    path.write_text(text)
    return path


def test_an_app_file_of_too_many_tasks_is_refused_before_any_runnable_is_built(tmp_path: Path) -> None:
    # the runnable does not exist: had a task been built, the error would name its module
    path = _tasks_file(tmp_path, unique_name("many"), MAX_TASKS + 1, "no_such_module_anywhere:Gain")
    with pytest.raises(AppFileError) as error:
        load_app(path)
    assert str(error.value).endswith(f"tasks: {MAX_TASKS + 1} tasks; an app has at most {MAX_TASKS} (each task is a "
                                     "process that locks its memory): let one task step several runnables, or "
                                     "split the app")


def test_the_cli_says_it_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _tasks_file(tmp_path, unique_name("many"), 200, "rt_test_runnables:Gain")
    code = main(["simulate", str(path), "--duration", "0.01", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "200 tasks; an app has at most 64" in err, err
    assert not (tmp_path / "out").exists()


def test_a_python_app_takes_64_tasks_and_refuses_the_65th() -> None:
    app = App(unique_name("many"))
    for i in range(MAX_TASKS):
        app.add_task(f"t{i}", Gain(1), period_ns=100_000_000, policy="other")
    with pytest.raises(AppError, match=f"^{MAX_TASKS + 1} tasks; an app has at most {MAX_TASKS} "):
        app.add_task("one_more", Gain(1), period_ns=100_000_000, policy="other")


def test_task_processes_that_would_not_fit_in_memory_are_refused() -> None:
    app = App(unique_name("mem"))
    for i in range(40):
        app.add_task(f"t{i}", Gain(1), period_ns=100_000_000, policy="other")
    mb = 1_000_000
    layout.check_task_memory(app, per_task_bytes=36 * mb, available=4000 * mb)  # 1440 MB of 4 GB: fits
    with pytest.raises(AppError) as error:
        layout.check_task_memory(app, per_task_bytes=36 * mb, available=2000 * mb)  # over half of 2 GB
    assert str(error.value) == (f"app {app.name!r}: 40 task processes of about 36.0 MB each would lock 1440.0 MB; "
                                "the machine has 2000.0 MB available and a run may lock at most 50% of it "
                                "(fewer tasks: let one task step several runnables)")


def test_a_run_checks_the_memory_before_it_starts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    name = unique_name("mem")
    path = _tasks_file(tmp_path, name, 3, "rt_test_runnables:Gain")
    monkeypatch.setattr(layout.memory, "available_bytes", lambda: 10_000_000)  # a machine with 10 MB to spare
    code = main(["run", str(path), "--duration", "5", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "3 task processes of about" in err and "10.0 MB available" in err, err
    assert not list(Path("/dev/shm").glob(f"rtloop-{name}-*"))  # nothing was created


def test_the_memory_figures_come_from_proc(tmp_path: Path) -> None:
    from rtloop.linux import memory

    (tmp_path / "meminfo").write_text("MemTotal:       24000000 kB\nMemAvailable:    2000000 kB\n")
    (tmp_path / "self").mkdir()
    (tmp_path / "self" / "status").write_text("Name:\tpython\nVmRSS:\t   36000 kB\n")
    assert memory.available_bytes(tmp_path) == 2_048_000_000
    assert memory.resident_bytes(proc=tmp_path) == 36_864_000
    assert memory.resident_bytes(4242, proc=tmp_path) is None  # no such process: nothing refused on it
    assert memory.available_bytes() > 0 and memory.resident_bytes() > 0  # this machine's /proc
