"""The devices' per-cycle work in C (``io/_devio.c``, one file per reference in ``io/devio_c/``), where it was built.

pip builds ``_devio`` with the system compiler next to the task's C hot path; without a
compiler, or with ``RTLOOP_PURE_PYTHON=1`` (the same switch as the hot path's), the Python
references run: the guard of ``io/limits.py``, the layouts of ``io/bytelayout.py``, the drain
of ``io/cansocket.py``, CAN's cycle in ``io/can.py``, GPIO's in ``io/gpio.py``, SPI's in
``io/spi.py`` and ``io/spiframe.py``, the servo packets' CRC-16, checksum and the sync read's
scan in ``io/servos/protocol.py``. Both give the same numbers, counts and errors (``tests/test_io_compiled.py``,
``tests/test_servo_checks.py``).
The switch is read when a device builds its cycle (``configure``), so a task process inherits it.

A build older than the sources beside it (a checkout changed after ``pip install -e .``) would
call objects with arguments they no longer take, or compute what the Python reference no longer
does: like the hot path's schema check, it is not used, and that is said once per process
(:func:`why_python`). So is a compiled object that refuses what its Python side gives it
(:func:`refused`).
"""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path
from typing import Any

from rtloop import build_check

PURE_PYTHON_ENV = "RTLOOP_PURE_PYTHON"
SOURCES_DIR = Path(__file__).resolve().parent
_said: set[str] = set()


def source_names(folder: Path = SOURCES_DIR) -> list[str]:
    """The C files ``_devio`` is built from, relative to ``io/``."""
    return sorted(["_devio.c", *(f"devio_c/{path.name}" for path in (folder / "devio_c").glob("*.c"))])


def sources_digest(folder: Path = SOURCES_DIR) -> str | None:
    """The digest setup.py gives the build (``_devio.SOURCES_DIGEST``), of the sources here now."""
    return build_check.sources_digest(folder, source_names(folder))


def _say_once(line: str) -> None:
    if line not in _said:
        _said.add(line)
        print(f"rtloop: {line}", file=sys.stderr)


def _stale(module: Any) -> str:
    """Why ``module`` is not the build of the sources here ("" when it is, or cannot be told)."""
    return build_check.stale_build(module, "the devices' C code (rtloop.io._devio)", sources_digest(),
                                   "io/_devio.c and io/devio_c/")


def why_python() -> str:
    """Why the devices' Python references run here ("" when the C build is used)."""
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0"):
        return f"{PURE_PYTHON_ENV}={os.environ[PURE_PYTHON_ENV]}"
    try:
        module = importlib.import_module("rtloop.io._devio")  # by name: C, which mypy cannot read
    except ImportError as error:
        return f"the devices' C code rtloop.io._devio is not built ({error})"
    return _stale(module)


def devio() -> Any:
    """The compiled module, or None where the Python references run (a stale build: said once)."""
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0"):
        return None
    try:
        module = importlib.import_module("rtloop.io._devio")
    except ImportError:
        return None  # no compiler at install: the hot path's announcement says it for both
    stale = _stale(module)
    if stale:
        _say_once(f"{stale}; the Python references run meanwhile")
        return None
    return module


def refused(what: str, error: BaseException) -> None:
    """A compiled object refused what its Python side gave it (a TypeError: the two sides disagree on
    a signature or a type): say so once, the Python reference runs."""
    _say_once(f"{what}: the compiled cycle refused its arguments ({type(error).__name__}: {error}); "
              "the Python reference runs (a build older than its sources? pip install -e .)")
