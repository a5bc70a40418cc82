"""What the commands share: argument types, the exit codes and the bad-input error."""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from pathlib import Path
from typing import Any, NoReturn

from rtloop.errors import RtloopError

EXIT_FAILED = 1
"""A run that failed: a task's fault, a check that failed, a bug."""
EXIT_BAD_INPUT = 2
"""What the user gave is wrong or incomplete (argparse's usage errors too, and a missing optional package)."""
EXIT_DEVICE_NOT_READY = 3
"""A device declared right refused at start (not there yet, busy, silent at configure): a service retries it."""
EXIT_INTERRUPTED = 130
"""Ctrl-C, as a shell reports death by SIGINT."""


class CommandParser(argparse.ArgumentParser):
    """The parser of ``rtloop`` and of each command. A usage error is one line naming the command and
    the argument (``rtloop top: argument --interval: must be ...; see rtloop top --help``), exit 2, as
    all bad input is; an argument a command does not know is its own error, not the root's. Each
    takes ``--debug``, so it may stand before or after the command's name."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # SUPPRESS: a command's parser must not reset what `rtloop --debug COMMAND` set
        self.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                          help="show the Python traceback behind an error")

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: {message} (see {self.prog} --help)\n")

    def parse_known_args(self, args: Iterable[str] | None = None,
                         namespace: Any = None) -> tuple[Any, list[str]]:
        parsed, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return parsed, extras


class BadInput(RtloopError, ValueError):
    """A value the parser could not judge alone (against another option, a file, the machine): exit 2."""


def positive_seconds(text: str) -> float:
    """A finite number of seconds > 0 (``--duration`` of a bench, ``--keep`` of a run)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text}")
    return value


def count(text: str) -> int:
    """A whole number ≥ 0 (``--trim`` of the statistics)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be ≥ 0, got {text}")
    return value


def at_least_one(text: str) -> int:
    """A whole number ≥ 1 (``--processes``)."""
    value = count(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text}")
    return value


def port_feed(text: str) -> tuple[str, Path]:
    """``PORT=FILE.csv`` (``--feed``: a profile that feeds an input port)."""
    port, sep, path = text.partition("=")
    if not sep or not port or not path:
        raise argparse.ArgumentTypeError(f"{text!r}: expected PORT=FILE.csv")
    return port, Path(path)
