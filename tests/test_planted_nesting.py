"""JSON nested 100,000 deep where rtloop reads JSON it did not write (a registry anyone may plant
in /dev/shm, the summary.json a registry names): listed as not a registry, no line, never an
internal error that stops ``rtloop port list`` or ``rtloop top`` for every user."""

from __future__ import annotations

import os
from pathlib import Path

from rtloop.cli.main import main
from rtloop.runtime.monitor import live_summary_line

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
