"""Exceptions survive pickling, and the rtloop command's exit codes follow one rule."""

from __future__ import annotations

import errno
import pickle
import sys
from pathlib import Path

import pytest

from rtloop.cli.main import EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_TASK_FAILED, exit_code_for
from rtloop.errors import AppError, AppFileError, DeviceError, LibcError, TaskFailed
from rtloop.runtime.session import RunDirectoryError

EXAMPLES = [
    TaskFailed("plant", 37, "step", "ValueError: boom", "Traceback (most recent call last): ..."),
    TaskFailed("plant", None, "prerun", "OSError: no device"),
    LibcError("sched_setscheduler", errno.EPERM, "needs CAP_SYS_NICE"),
    LibcError("mlockall", errno.ENOMEM),
    AppFileError("app.toml", "tasks.pi.period_ns", "expected an integer"),
    DeviceError("motor", "app.toml", "port", "no such file"),
    RunDirectoryError("runs/x already holds a run"),
]


@pytest.mark.parametrize("error", EXAMPLES, ids=lambda e: type(e).__name__)
def test_an_error_survives_pickling_whole(error: Exception) -> None:
    copy = pickle.loads(pickle.dumps(error))
    assert type(copy) is type(error)
    assert str(copy) == str(error)
    assert vars(copy) == vars(error)
    assert copy.args == error.args


def test_libc_error_keeps_its_errno_and_call() -> None:
    copy = pickle.loads(pickle.dumps(LibcError("mlockall", errno.ENOMEM, "raise ulimit -l")))
    assert (copy.call, copy.errno, copy.hint) == ("mlockall", errno.ENOMEM, "raise ulimit -l")
    assert isinstance(copy, OSError)


@pytest.mark.parametrize(("error", "code"), [
    (AppError("bad"), EXIT_BAD_INPUT),
    (AppFileError("a.toml", "k", "p"), EXIT_BAD_INPUT),
    (RunDirectoryError("taken"), EXIT_BAD_INPUT),
    (ModuleNotFoundError("No module named 'fmpy'", name="fmpy"), EXIT_BAD_INPUT),  # a missing extra is bad input
    (TaskFailed("t", 1, "step", "boom"), EXIT_TASK_FAILED),
    (LibcError("mlockall", errno.ENOMEM), EXIT_TASK_FAILED),
    (LibcError("sched_setscheduler", errno.EPERM), EXIT_TASK_FAILED),
    (OSError(errno.ENOTDIR, "Not a directory", "/dev/null/x"), EXIT_BAD_INPUT),  # a path the user gave
    (OSError(errno.EROFS, "Read-only file system", "/usr/x"), EXIT_BAD_INPUT),
    (OSError(errno.ENOSPC, "No space left on device", "runs/x"), EXIT_TASK_FAILED),  # a full disk: the run failed
    (RuntimeError("a bug"), EXIT_TASK_FAILED),
    (KeyboardInterrupt(), EXIT_INTERRUPTED),
])
def test_exit_codes_follow_one_rule(error: BaseException, code: int) -> None:
    assert exit_code_for(error) == code


def test_a_missing_optional_package_exits_2_from_the_command(capsys, monkeypatch) -> None:
    from rtloop.cli import main as cli

    for name in list(sys.modules):
        if name.split(".")[0] == "matplotlib" or name.startswith("rtloop.report"):
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ModuleNotFoundError
    assert cli.main(["report", "somewhere"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.startswith("rtloop report: ") and "pip install 'rtloop[report]'" in err
    assert len(err.strip().splitlines()) == 1


def test_a_path_that_cannot_be_written_is_one_line_and_exit_2(tmp_path, capsys) -> None:
    pytest.importorskip("matplotlib", reason="the report needs matplotlib (pip install 'rtloop[report]')")
    from rtloop.cli.main import main

    primes = Path(__file__).resolve().parents[1] / "examples" / "primes" / "primes.toml"
    assert main(["simulate", str(primes), "--duration", "0.1", "--out", str(tmp_path / "run"), "--quiet"]) == 0
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    code = main(["report", str(tmp_path / "run"), "--out", str(blocker / "report")])
    err = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT and len(err.strip().splitlines()) == 1, err
    assert str(blocker) in err and "Not a directory" in err and "internal error" not in err, err
