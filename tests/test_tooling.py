"""The strict tooling stays strict and explained: every exception to ruff or mypy carries its reason
on its own line, and CI runs both before the suite."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = ROOT / "pyproject.toml"


def _lines_of(table: str) -> list[str]:
    """The lines of one ``[table]`` (or ``[[table]]``) block of pyproject.toml, every occurrence."""
    lines, inside = [], False
    for line in PYPROJECT.read_text().splitlines():
        if line.startswith("["):
            inside = line.strip("[] ") == table
        elif inside:
            lines.append(line)
    return lines


def test_mypy_is_strict_on_src() -> None:
    config = tomllib.loads(PYPROJECT.read_text())["tool"]["mypy"]
    assert config["strict"] is True
    assert config["files"] == ["src"]
    test_extra = tomllib.loads(PYPROJECT.read_text())["project"]["optional-dependencies"]["test"]
    assert any(re.match(r"mypy\b", requirement) for requirement in test_extra)


def test_every_mypy_override_says_why() -> None:
    overrides = tomllib.loads(PYPROJECT.read_text())["tool"]["mypy"].get("overrides", [])
    module_lines = [line for line in _lines_of("tool.mypy.overrides") if line.startswith("module")]
    assert len(module_lines) == len(overrides)
    for line in module_lines:
        assert re.search(r"#\s*\S", line), f"pyproject.toml: mypy override without its reason: {line}"
    for override in overrides:  # switches rules off per module, never a whole module's checking
        assert set(override) <= {"module", "ignore_missing_imports"}, override


def test_every_ruff_ignore_says_why() -> None:
    ignored = tomllib.loads(PYPROJECT.read_text())["tool"]["ruff"]["lint"].get("ignore", [])
    text = PYPROJECT.read_text()
    for rule in ignored:
        line = next(line for line in text.splitlines() if f'"{rule}"' in line and "ignore" not in line)
        assert re.search(r"#\s*\S", line), f"pyproject.toml: ruff ignore {rule} without its reason"


def test_ci_runs_ruff_and_mypy_before_the_suite() -> None:
    script = (ROOT / ".ci" / "run").read_text().splitlines()
    commands = [line.strip() for line in script if line.strip() and not line.lstrip().startswith(("#", "echo"))]
    setup = commands.index("tools/setup.sh")
    ruff = next(i for i, c in enumerate(commands) if c.startswith(".venv/bin/ruff check"))
    mypy = next(i for i, c in enumerate(commands) if c.startswith(".venv/bin/mypy"))
    suite = next(i for i, c in enumerate(commands) if c.startswith('eval "$test_command"'))
    assert setup < ruff < suite and setup < mypy < suite
    assert "set -euo pipefail" in script  # either failing stops CI
