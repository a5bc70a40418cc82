"""rtloop: real-time control loops in Python on Linux.

Write a :class:`Runnable`, add it to an :class:`App` as a periodic task, wire tasks
with ``app.connect``, reach them from non-real-time code through ports, then
``rtloop.run(app, ...)`` (real time) or ``rtloop.simulate(app, ...)`` (offline, lock-step).
"""

import importlib
from typing import TYPE_CHECKING, Any

from rtloop.app.builder import App as App
from rtloop.app.builder import SignalRef as SignalRef
from rtloop.errors import AppError as AppError
from rtloop.errors import AppFileError as AppFileError
from rtloop.errors import ConnectionSizeError as ConnectionSizeError
from rtloop.errors import LibcError as LibcError
from rtloop.errors import PortValueError as PortValueError
from rtloop.errors import RtloopError as RtloopError
from rtloop.errors import StopRequested as StopRequested
from rtloop.errors import TaskFailed as TaskFailed
from rtloop.runnable import Runnable as Runnable
from rtloop.runnable import TickInfo as TickInfo
from rtloop.stats.timing import TaskTiming as TaskTiming
from rtloop.version import __version__ as __version__

if TYPE_CHECKING:
    from rtloop.record.load import RunData as RunData
    from rtloop.record.load import load as load
    from rtloop.record.summary import RunSummary as RunSummary
    from rtloop.record.summary import TaskSummary as TaskSummary
    from rtloop.runtime.simulate import simulate as simulate
    from rtloop.runtime.supervisor import run as run
    from rtloop.runtime.sweep import sweep as sweep

# Imported on first use, not here: every task process imports this package (it unpickles
# rtloop.runtime.task), and the supervisor, the recorder and their dependencies would
# otherwise be loaded, and locked into memory by mlockall, in each of them.
_LAZY = {
    "RunData": "rtloop.record.load",
    "load": "rtloop.record.load",
    "RunSummary": "rtloop.record.summary",
    "TaskSummary": "rtloop.record.summary",
    "simulate": "rtloop.runtime.simulate",
    "run": "rtloop.runtime.supervisor",
    "sweep": "rtloop.runtime.sweep",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'rtloop' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value

__all__ = [
    "App",
    "AppError",
    "AppFileError",
    "ConnectionSizeError",
    "LibcError",
    "PortValueError",
    "RtloopError",
    "RunData",
    "RunSummary",
    "Runnable",
    "SignalRef",
    "StopRequested",
    "TaskFailed",
    "TaskSummary",
    "TaskTiming",
    "TickInfo",
    "load",
    "run",
    "simulate",
    "sweep",
]
