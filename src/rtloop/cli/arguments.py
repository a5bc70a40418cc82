"""Argument types the commands share."""

from __future__ import annotations

import argparse


def positive_seconds(text: str) -> float:
    """A finite number of seconds > 0 (``--duration`` of a bench, ``--keep`` of a run)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text}")
    return value
