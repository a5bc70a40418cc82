"""rtloop: real-time control loops in Python on Linux.

Write a :class:`Runnable`, add it to an :class:`App` as a periodic task, wire tasks
with ``app.connect``, reach them from non-real-time code through ports, then
``rtloop.run(app, ...)`` (real time) or ``rtloop.simulate(app, ...)`` (offline, lock-step).
"""

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
from rtloop.record.summary import RunSummary as RunSummary
from rtloop.record.summary import TaskSummary as TaskSummary
from rtloop.runnable import Runnable as Runnable
from rtloop.runnable import TickInfo as TickInfo
from rtloop.runtime.simulate import simulate as simulate
from rtloop.runtime.supervisor import run as run
from rtloop.timing import TaskTiming as TaskTiming
from rtloop.version import __version__ as __version__

__all__ = [
    "App",
    "AppError",
    "AppFileError",
    "ConnectionSizeError",
    "LibcError",
    "PortValueError",
    "RtloopError",
    "RunSummary",
    "Runnable",
    "SignalRef",
    "StopRequested",
    "TaskFailed",
    "TaskSummary",
    "TaskTiming",
    "TickInfo",
    "run",
    "simulate",
]
