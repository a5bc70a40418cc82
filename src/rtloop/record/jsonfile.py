"""JSON files of a run folder (summary.json, replay.json, signals.json), read as data that may be
damaged or planted: a file nested 100,000 deep is a ValueError like any other bad JSON, which
every reader already turns into one line naming the file — never a RecursionError."""

from __future__ import annotations

import json
from typing import Any


def parse_json(text: str | bytes) -> Any:
    """``json.loads``, with nesting too deep for the parser a :class:`ValueError` too."""
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError("nested too deeply to be read; not a file rtloop wrote") from None
