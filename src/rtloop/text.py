"""Cutting what an error message quotes down to size: a message names bad input, never prints 5 MB of it."""

from __future__ import annotations

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
