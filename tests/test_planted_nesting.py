"""JSON nested 100,000 deep where rtloop reads JSON it did not write (a registry anyone may plant
in /dev/shm, the summary.json a registry names): listed as not a registry, no line, never an
internal error that stops ``rtloop port list`` or ``rtloop top`` for every user."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from rtloop.cli.main import main
from rtloop.toolbox.monitor import live_summary_line

DEEP = "[" * 100_000 + "]" * 100_000


def test_a_planted_registry_nested_too_deeply_is_listed_not_a_crash(capsys) -> None:
    planted = Path(f"/dev/shm/rtloop-deepplant{os.getpid()}-{os.getpid()}-deadbeef-registry.json")
    planted.write_text(DEEP)
    try:
        assert main(["port", "list"]) == 0
        out_err = capsys.readouterr()
        assert f"{planted.name}: nested too deeply; not a registry" in out_err.out + out_err.err
        code = main(["top", "--once"])
        err = capsys.readouterr().err
        assert "internal error" not in err and code in (0, 1), err
    finally:
        planted.unlink()


def test_a_summary_nested_too_deeply_gives_no_line(tmp_path: Path) -> None:
    summary = tmp_path / "summary.json"
    summary.write_text(DEEP)
    assert live_summary_line(str(summary)) == ""


@pytest.fixture(scope="module")
def a_run(tmp_path_factory) -> Path:
    import rtloop
    from rt_test_runnables import Counter

    app = rtloop.App(f"deeprun_{os.getpid()}")
    task = app.add_task("c", Counter(), period_ns=1_000_000)
    app.record(task.y)
    out = tmp_path_factory.mktemp("deeprun") / "run"
    rtloop.simulate(app, 0.01, out)
    return out


@pytest.mark.parametrize("damaged", ["summary.json", "replay.json", "signals.json"])
def test_a_run_file_nested_too_deeply_is_one_line_for_load_report_and_replay(a_run: Path, tmp_path: Path,
                                                                            damaged: str, capsys) -> None:
    import shutil

    import rtloop
    from rtloop.errors import RtloopError
    from rtloop.runtime.replay import load_replay_app

    run = tmp_path / "run"
    shutil.copytree(a_run, run)
    (run / damaged).write_text(DEEP)
    if damaged == "summary.json":
        with pytest.raises(RtloopError, match=r"summary\.json: unreadable: nested too deeply"):
            rtloop.load(run)
        assert main(["report", str(run)]) == 2
        assert "nested too deeply" in capsys.readouterr().err
    elif damaged == "replay.json":
        with pytest.raises(RtloopError, match=r"replay\.json: not readable JSON \(nested too deeply"):
            load_replay_app(run)
    else:
        loaded = rtloop.load(run)  # the signals load without their units, and it says why
        assert any("signals.json: unreadable" in problem for problem in loaded.problems)
