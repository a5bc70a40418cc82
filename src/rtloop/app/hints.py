"""What an app's author is told where a name or a warning would otherwise leave them guessing.

``did you mean`` for a signal name close to one the app has, and warnings found while a task is
added (a model's step size) pointed at the user's own line: the app file's ``[tasks.NAME]``
table, or the line of their script that added the task, not rtloop's own files.
"""

from __future__ import annotations

import difflib
import re
import sys
import warnings
from pathlib import Path
from typing import Any

from rtloop.text import shorten

PACKAGE_DIR = str(Path(__file__).resolve().parents[1])
PYTHON_APP = "<python>"
"""``App.source`` of an app built in Python (not loaded from an app file)."""


def signal_hint(text: str, app: Any) -> str:
    """`` (did you mean 'lqr.force_N'?)`` for ``text`` (``task.name``) close to a signal ``app`` has,
    else the task's signal names; '' when there is nothing to offer."""
    task, dot, name = text.strip().partition(".")
    if not dot:
        return ""
    block = app.block(task)
    if block is None:
        close = difflib.get_close_matches(task, list(app.tasks), n=1)
        return f" (did you mean {close[0] + dot + name!r}?)" if close else ""
    named = getattr(block, "runnable", None) or getattr(block, "device", None)
    names = [str(n) for side in ("output_names", "input_names") for n in (getattr(named, side, None) or ())]
    close = difflib.get_close_matches(name, names, n=1, cutoff=0.5)
    if close:
        return f" (did you mean {task + '.' + close[0]!r}?)"
    return f" (the signals {task} names: {shorten(names)})" if names else ""


def reissue_at_user(caught: list[warnings.WarningMessage], app_source: str, task: str) -> None:
    """Warn again with each warning ``caught`` while task ``task`` was added, at the user's line."""
    for warning in caught:
        filename, lineno = _task_line(app_source, task) if app_source != PYTHON_APP else _caller_outside_rtloop()
        warnings.warn_explicit(warning.message, warning.category, filename, lineno)


def _task_line(app_file: str, task: str) -> tuple[str, int]:
    """The app file and the line of its ``[tasks.NAME]`` table (1 when it cannot be found)."""
    pattern = re.compile(rf"^\s*\[\s*tasks\s*\.\s*[\"']?{re.escape(task)}[\"']?\s*\]")
    try:
        with open(app_file, encoding="utf-8", errors="replace") as file:
            for number, line in enumerate(file, start=1):
                if pattern.match(line):
                    return app_file, number
    except OSError:
        pass
    return app_file, 1


def _caller_outside_rtloop() -> tuple[str, int]:
    """The innermost frame of the call stack that is not in rtloop's own files: the user's line."""
    frame = sys._getframe(1)
    while frame.f_back is not None and frame.f_code.co_filename.startswith(PACKAGE_DIR):
        frame = frame.f_back
    return frame.f_code.co_filename, frame.f_lineno
