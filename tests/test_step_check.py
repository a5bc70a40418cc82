"""A step that returns its outputs, or rebinds y, and never writes into y is warned about when its
task is added (its outputs would stay 0 without a word); one that writes into y is not."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import rtloop
from rtloop.app.step_check import StepWarning, function_problem, step_problem


class Returns(rtloop.Runnable):
    n_inputs, n_outputs = 1, 1

    def step(self, u, y):
        return 2.0 * u[0] + 1.0


class Rebinds(rtloop.Runnable):
    n_inputs, n_outputs = 1, 1

    def step(self, u, y):
        y = np.array([2.0 * u[0] + 1.0])  # noqa: F841 - the mistake under test


class FillsAndReturns(rtloop.Runnable):
    n_inputs, n_outputs = 1, 1

    def step(self, u, y):
        y[0] = 2.0 * u[0]
        return y


class Other(rtloop.Runnable):
    """In-place writes of every kind, names of one's own, a helper defined inside: all fine."""

    n_inputs, n_outputs = 2, 2

    def step(self, inputs, outputs):
        def helper():
            return 1.0
        np.copyto(outputs, inputs)
        outputs += helper()


class Fills(rtloop.Runnable):
    n_inputs, n_outputs = 1, 1

    def step(self, u, y):
        y[:] = u
        return None


def test_the_two_mistakes_are_found_with_their_line() -> None:
    returned = step_problem(Returns) or ""
    assert "Returns.step returns a value" in returned and "return 2.0 * u[0] + 1.0" in returned
    assert "write them in place (y[0] = ..." in returned
    rebound = step_problem(Rebinds) or ""
    assert "Rebinds.step assigns a new object to y" in rebound and "(line " in rebound
    for fine in (FillsAndReturns, Other, Fills):
        assert step_problem(fine) is None, fine


def test_adding_such_a_task_warns_once_and_the_app_still_runs(tmp_path) -> None:
    app = rtloop.App(f"stepwarn_{__import__('os').getpid()}")
    with pytest.warns(StepWarning, match="task 'ret': Returns.step returns a value"):
        app.add_task("ret", Returns(), period_ns=10_000_000)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        app.add_task("fine", Fills(), period_ns=10_000_000)  # no warning


def test_no_step_the_project_ships_is_flagged() -> None:
    """Every step in examples/, src/ and tests/ writes into its y, but this file's two mistakes."""
    import ast
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    flagged = []
    for path in [*root.joinpath("examples").rglob("*.py"), *root.joinpath("src").rglob("*.py"),
                 *root.joinpath("tests").rglob("*.py")]:
        text = path.read_text()
        if not re.search(r"\bdef[\s\\]+step\b", text):  # no step defined here: not worth parsing
            continue
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef) and node.name == "step" and function_problem(node, "step"):
                flagged.append(f"{path.name}:{node.lineno}")
    assert sorted(flagged) == ["test_step_check.py:18", "test_step_check.py:25"], flagged
