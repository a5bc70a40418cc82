"""The ``rtloop`` command is one argparse tree: every command answers ``--help`` (exit 0) and
refuses an unknown option or a bad value with one line naming the command and the argument
(exit 2, no traceback); building the tree, and ``rtloop port write``, import no heavy engine
(behaviour: ``sys.modules`` in a fresh interpreter, not time)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections.abc import Iterator

import pytest

from rtloop.cli.main import COMMANDS, build_parser, main

# Engines and optional packages a command loads when it runs, never for parsing.
HEAVY = ("rich", "matplotlib", "cyclonedds", "mcap", "mcap_ros2", "foxglove", "fmpy", "serial",
         "rtloop.report", "rtloop.ros.bridge", "rtloop.ros.dds", "rtloop.ros.live", "rtloop.runtime.supervisor",
         "rtloop.runtime.simulate", "rtloop.runtime.replay", "rtloop.toolbox.sweep", "rtloop.record.recorder",
         "rtloop.cli.top_view", "rtloop.app.appfile")


def subcommand_paths(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> Iterator[tuple[str, ...]]:
    """Every command and nested command of the tree (``("port", "write")``, ...), parents first."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*path, name)
                yield from subcommand_paths(sub, (*path, name))


PATHS = sorted(subcommand_paths(build_parser()))


def test_every_command_is_in_the_tree() -> None:
    top_level = {path[0] for path in PATHS}
    assert top_level == set(COMMANDS) == {
        "run", "simulate", "replay", "port", "model", "report", "top", "doctor", "bridge", "bench", "service",
        "io", "sweep", "why", "switch", "emulate", "reload"}
    assert {("port", "write"), ("port", "read"), ("port", "list"), ("model", "info"), ("model", "build"),
            ("bridge", "listener"), ("bridge", "talker"), ("io", "list")} <= set(PATHS)


@pytest.mark.parametrize("path", PATHS, ids=" ".join)
def test_help_exits_0(path: tuple[str, ...], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([*path, "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: rtloop {' '.join(path)}"), out


@pytest.mark.parametrize("path", PATHS, ids=" ".join)
def test_an_unknown_option_is_a_usage_error(path: tuple[str, ...], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([*path, "--no-such-option"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err  # one line
    assert err.startswith(f"rtloop {path[0]}")  # the command that refused (or its nested one)
    assert "--no-such-option" in err or "required" in err or "invalid choice" in err, err
    assert err.rstrip().endswith("--help)")  # where to look


@pytest.mark.parametrize(("argv", "named"), [
    (["top", "--interval", "0"], "--interval"),
    (["bench", "affinity", "--trim", "-1"], "--trim"),
    (["run", "app.toml", "--out", "x", "--keep", "nan"], "--keep"),
    (["run", "app.toml", "--out", "x", "--feed", "nonsense"], "--feed"),
    (["bridge", "listener", "--app", "a", "--port", "p", "--topic", "/t", "--type", "std_msgs/msg/String"], "--type"),
    (["report"], "DIR"),
    (["simulate", "app.toml", "--out", "x", "--trim", "-1"], "--trim"),
    (["sweep", "app.toml", "--duration", "1", "--processes", "0"], "--processes"),
    (["sweep", "app.toml", "--duration", "1", "--feed", "setpoint"], "--feed"),
    (["port", "read", "app", "port", "--count", "0"], "--count"),
    ([], "COMMAND"),
    (["nonsense"], "invalid choice: 'nonsense'"),
])
def test_a_bad_value_names_its_argument(argv: list[str], named: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and named in err, err


def test_bad_input_found_by_a_command_is_one_line_and_exit_2(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report", str(tmp_path / "no-such-run")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("rtloop report: ") and err.count("\n") == 1, err
    assert main(["service", str(tmp_path / "none.toml"), "--keep", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("rtloop service: --keep 0") and err.count("\n") == 1, err


def _modules_after(code: str, rtloop_env: dict[str, str], heavy: tuple[str, ...] = HEAVY) -> tuple[list[str], str]:
    """The ``heavy`` modules loaded by ``code`` in a fresh interpreter, and its stderr."""
    probe = (f"import json, sys\n{code}\n"
             f"heavy = {heavy!r}\n"
             "below = tuple(h + '.' for h in heavy)\n"
             "print(json.dumps(sorted(m for m in sys.modules if m in heavy or m.startswith(below))))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=rtloop_env, timeout=60)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1]), result.stderr


def test_building_the_tree_imports_no_engine(rtloop_env: dict[str, str]) -> None:
    loaded, _ = _modules_after("from rtloop.cli.main import build_parser\nbuild_parser().format_help()", rtloop_env)
    assert loaded == []


def test_help_loads_no_numpy(rtloop_env: dict[str, str]) -> None:
    """``rtloop --help`` (and a usage error) answer without numpy or the app description:
    the package's top-level names are imported on first use (``rtloop/__init__.py``)."""
    light = ("numpy", "rtloop.app", "rtloop.runnable", "rtloop.stats.timing", "rtloop.toolbox.bench")
    for argv in (["--help"], ["bench", "--help"], ["service", "--help"], ["top", "--interval", "0"]):
        code = f"from rtloop.cli.main import main\ntry:\n    main({argv!r})\nexcept SystemExit:\n    pass"
        loaded, _ = _modules_after(code, rtloop_env, light)
        assert loaded == [], (argv, loaded)
    # The check can fail: a command that works with values (a port client) loads numpy.
    loaded, _ = _modules_after("from rtloop.cli.main import main\nmain(['port', 'write', 'no_app', 'x', '1'])",
                               rtloop_env, light)
    assert "numpy" in loaded


def test_the_heavy_modules_are_heavy(rtloop_env: dict[str, str]) -> None:
    """The check above can fail: a command that runs does load its engine."""
    pytest.importorskip("matplotlib", reason="the report engine needs matplotlib (pip install 'rtloop[report]')")
    loaded, _ = _modules_after("from rtloop.cli.main import main\nmain(['report', '/nonexistent-run-dir'])",
                               rtloop_env)
    assert "matplotlib" in loaded and "rtloop.report.build" in loaded


def test_port_write_imports_no_engine(rtloop_env: dict[str, str]) -> None:
    code = "from rtloop.cli.main import main\ncode = main(['port', 'write', 'no_such_app_cli_tree', 'x', '1'])"
    loaded, err = _modules_after(code, rtloop_env)
    assert loaded == []
    assert "no_such_app_cli_tree" in err and "Traceback" not in err


@pytest.mark.parametrize("argv", [["--debug", "report"], ["report", "--debug"]])
def test_debug_shows_the_traceback_before_or_after_the_command(argv: list[str], tmp_path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    assert main([*argv, str(tmp_path / "no-such-run")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and err.rstrip().splitlines()[-1].startswith("rtloop report: ")


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    from rtloop.version import __version__

    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0 and capsys.readouterr().out == f"rtloop {__version__}\n"
