"""The package's top level (``rtloop/__init__.py``): every public name works as
``from rtloop import X`` and ``rtloop.X``, is known to ``dir()`` and to type checkers, and
``import rtloop`` itself loads neither numpy nor an engine (behaviour: ``sys.modules`` in a
fresh interpreter)."""

from __future__ import annotations

import ast
import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

import rtloop

INIT = Path(rtloop.__file__)


def _fresh(code: str, rtloop_env: dict[str, str]) -> object:
    """What ``code`` prints as JSON on its last line, run in a fresh interpreter."""
    result = subprocess.run([sys.executable, "-c", f"import json, sys\n{code}"], capture_output=True, text=True,
                            env=rtloop_env, timeout=60)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_import_rtloop_loads_no_numpy(rtloop_env: dict[str, str]) -> None:
    loaded = _fresh("import rtloop\nprint(json.dumps(sorted(m for m in sys.modules "
                    "if m == 'numpy' or m.startswith('rtloop.'))))", rtloop_env)
    assert loaded == ["rtloop.errors", "rtloop.version"]


@pytest.mark.parametrize("name", rtloop.__all__)
def test_from_rtloop_import_each_name_in_a_fresh_interpreter(name: str, rtloop_env: dict[str, str]) -> None:
    origin = _fresh(f"from rtloop import {name}\nimport rtloop\n"
                    f"assert rtloop.{name} is {name}\n"
                    f"print(json.dumps(getattr({name}, '__module__', None)))", rtloop_env)
    assert origin == getattr(rtloop, name).__module__


def test_each_name_is_the_object_of_its_module() -> None:
    tree = ast.parse(INIT.read_text())
    declared: dict[str, str] = {}  # name -> module, from every import of the file (eager or TYPE_CHECKING)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("rtloop"):
            for alias in node.names:
                declared[alias.asname or alias.name] = node.module
    assert set(rtloop.__all__) <= set(declared), "a public name type checkers do not see"
    for name in rtloop.__all__:
        assert getattr(rtloop, name) is getattr(importlib.import_module(declared[name]), name), name
    assert set(rtloop._LAZY) <= set(rtloop.__all__)
    assert {name: declared[name] for name in rtloop._LAZY} == rtloop._LAZY  # the same module for both


def test_dir_knows_every_public_name_before_its_first_use(rtloop_env: dict[str, str]) -> None:
    missing = _fresh("import rtloop\nprint(json.dumps(sorted(set(rtloop.__all__) - set(dir(rtloop)))))", rtloop_env)
    assert missing == []


def test_an_unknown_name_is_an_attribute_error() -> None:
    with pytest.raises(AttributeError, match="module 'rtloop' has no attribute 'Nonsense'"):
        rtloop.Nonsense  # noqa: B018
    with pytest.raises(ImportError):
        exec("from rtloop import Nonsense", {})
