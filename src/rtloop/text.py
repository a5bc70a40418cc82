"""Cutting what an error message quotes down to size (a message names bad input, never prints 5 MB of it);
counts in words; the user's own frames of a traceback."""

from __future__ import annotations

import os

ELLIPSIS = "…"


def clip(text: str, limit: int = 80, *, keep_end: int = 0) -> str:
    """``text`` in at most ``limit`` characters; a cut is marked with "…", and the last
    ``keep_end`` characters stay (a closing quote or bracket shows the value ended there)."""
    if len(text) <= limit:
        return text
    keep_end = min(keep_end, max(limit - 1, 0))
    head = max(limit - 1 - keep_end, 0)
    return text[:head] + ELLIPSIS + (text[-keep_end:] if keep_end else "")


def shorten(value: object, limit: int = 80) -> str:
    """``repr(value)`` clipped to ``limit`` characters, keeping its last four: for quoting input."""
    return clip(repr(value), limit, keep_end=4)


def counted(count: int, noun: str, plural: str | None = None) -> str:
    """``1 port input``, ``2 port inputs``: a count with its noun in the right number."""
    return f"{count} {noun if count == 1 else plural or noun + 's'}"


FRAMEWORK_PATH_PARTS = (f"{os.path.dirname(os.path.abspath(__file__))}{os.sep}", "/src/rtloop/", "/site-packages/",
                        "/dist-packages/", "/lib/python3", "<frozen ")
"""A traceback frame whose file path holds one of these is rtloop's (this package, wherever it was when
the run was recorded), a library's or Python's, not the user's."""


def user_frames(traceback_text: str) -> list[str]:
    """The frames of a formatted Python traceback that are in the user's own files (each its
    ``File "…", line N, in f`` line and the source line below it), outermost first."""
    lines = traceback_text.splitlines()
    out: list[str] = []
    for index, line in enumerate(lines):
        stripped = line.strip()
        if not stripped.startswith('File "'):
            continue
        path = stripped[len('File "'):].partition('"')[0]
        if any(part in path for part in FRAMEWORK_PATH_PARTS):
            continue
        out.append(stripped)
        following = lines[index + 1].strip() if index + 1 < len(lines) else ""
        if following and not following.startswith(("File \"", "Traceback", "During handling", "The above")):
            out.append("    " + following)
    return out
