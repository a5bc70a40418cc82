"""The devices' per-cycle work in C (``io/_devio.c``), where it was built.

pip builds ``_devio`` with the system compiler next to the task's C hot path; without a
compiler, or with ``RTLOOP_PURE_PYTHON=1`` (the same switch as the hot path's), the Python
references run: the guard of ``io/limits.py``, the layouts of ``io/bytelayout.py``, the drain
of ``io/cansocket.py``, CAN's cycle in ``io/can.py``, GPIO's in ``io/gpio.py``, SPI's in
``io/spi.py`` and ``io/spiframe.py``. Both give the same numbers, counts and errors (``tests/test_io_compiled.py``).
The switch is read when a device builds its cycle (``configure``), so a task process inherits it.
"""

from __future__ import annotations

import importlib
import os
from typing import Any

PURE_PYTHON_ENV = "RTLOOP_PURE_PYTHON"


def devio() -> Any:
    """The compiled module, or None where the Python references run."""
    if os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0"):
        return None
    try:
        return importlib.import_module("rtloop.io._devio")  # by name: C, which mypy cannot read
    except ImportError:
        return None
