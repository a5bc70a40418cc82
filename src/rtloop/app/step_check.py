"""The two commonest first-week mistakes in a ``step``, found in its source when a task is added.

rtloop hands ``step(u, y)`` the task's own output vector and reads it afterwards; what ``step``
returns is ignored. Every other framework a student knows returns the output, so two mistakes
come first, and both run "fine" with outputs that stay 0:

- ``return 2.0 * u[0]``: the value goes nowhere;
- ``y = np.array([...])``: the name now means a new array; the task's vector is untouched.

Either is reported (a :class:`StepWarning`, once, when the task is added) only when the
``step`` never writes into ``y`` in place (``y[0] = ...``, ``y[:] = ...``, ``y += ...``,
``np.copyto(y, ...)``, ``y.fill(...)``): a step that fills ``y`` and also returns it is fine.
Nothing runs: the check reads the method's source, and says nothing where there is none
(a compiled or generated model).
"""

from __future__ import annotations

import ast
import inspect
import textwrap
import warnings
from typing import Any


class StepWarning(UserWarning):
    """A ``step`` that returns its outputs, or rebinds ``y``, instead of writing into ``y``."""


def warn_about_step(task: str, runnable: Any) -> None:
    """Warn once if ``runnable.step`` returns a value or rebinds ``y`` and never writes into ``y``."""
    problem = step_problem(type(runnable))
    if problem is not None:
        warnings.warn(f"task {task!r}: {problem}", StepWarning, stacklevel=3)


def step_problem(cls: type) -> str | None:
    """What is wrong with ``cls.step`` (None: nothing found, or no source to read)."""
    step = getattr(cls, "step", None)
    function = _parse(step)
    if function is None:
        return None
    first_line = inspect.getsourcelines(step)[1] - 1 if step is not None else 0
    return function_problem(function, f"{cls.__name__}.step", first_line)


def function_problem(function: ast.FunctionDef, name: str, first_line: int = 0) -> str | None:
    """What is wrong with the ``step`` method ``function`` (parsed), shown as ``name``."""
    parameters = [a.arg for a in function.args.posonlyargs + function.args.args]
    if len(parameters) < 3:
        return None
    y_name = parameters[2]
    body = list(_own_nodes(function))
    if any(_writes_into(node, y_name) for node in body):
        return None
    for node in body:
        if isinstance(node, ast.Return) and node.value is not None and not _is_none(node.value):
            return (f"{name} returns a value (line {first_line + node.lineno}: return "
                    f"{ast.unparse(node.value)[:60]}) and never writes into {y_name}: rtloop ignores what step "
                    f"returns and reads {y_name}, so the outputs stay as they were; write them in place "
                    f"({y_name}[0] = ..., {y_name}[:] = ...)")
        if isinstance(node, ast.Assign | ast.AnnAssign) and any(
                isinstance(target, ast.Name) and target.id == y_name for target in _targets(node)):
            return (f"{name} assigns a new object to {y_name} (line {first_line + node.lineno}) and never "
                    f"writes into it: the task's outputs stay as they were; write them in place "
                    f"({y_name}[0] = ..., {y_name}[:] = ...)")
    return None


def _parse(step: Any) -> ast.FunctionDef | None:
    if step is None or getattr(step, "__isabstractmethod__", False):
        return None
    try:
        source = textwrap.dedent(inspect.getsource(step))
        tree = ast.parse(source)
    except (OSError, TypeError, SyntaxError, IndentationError):
        return None
    function = tree.body[0] if tree.body else None
    return function if isinstance(function, ast.FunctionDef) else None


def _own_nodes(function: ast.FunctionDef) -> Any:
    """The nodes of ``function``'s body, not those of functions or classes defined inside it."""
    stack: list[ast.AST] = list(function.body)
    while stack:
        node = stack.pop()
        yield node
        if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda | ast.ClassDef):
            stack.extend(ast.iter_child_nodes(node))


def _targets(node: ast.Assign | ast.AnnAssign) -> list[ast.expr]:
    return node.targets if isinstance(node, ast.Assign) else [node.target]


def _is_none(value: ast.expr) -> bool:
    return isinstance(value, ast.Constant) and value.value is None


def _writes_into(node: ast.AST, y_name: str) -> bool:
    """``y[...] = ...``, ``y += ...``, ``y.attr...(...)`` or ``f(..., y, ...)`` (np.copyto(y, x))."""
    if isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Store):
        return _is(node.value, y_name)
    if isinstance(node, ast.AugAssign):
        return _is(node.target, y_name)
    if isinstance(node, ast.Call):
        if isinstance(node.func, ast.Attribute) and _is(node.func.value, y_name):
            return True
        return any(_is(argument, y_name) for argument in [*node.args, *(k.value for k in node.keywords)])
    return False


def _is(node: ast.AST, name: str) -> bool:
    while isinstance(node, ast.Subscript | ast.Attribute):  # y[0][1] = ..., y.flat[0] = ...
        node = node.value
    return isinstance(node, ast.Name) and node.id == name
