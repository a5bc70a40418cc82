"""rtloop: real-time control loops in Python on Linux.

Write a :class:`Runnable`, add it to an :class:`App` as a periodic task, wire tasks
with ``app.connect``, reach them from non-real-time code through ports, then
``app.run`` (real time) or ``app.simulate`` (offline, lock-step).
"""

from .app import App as App
from .app import SignalRef as SignalRef
from .errors import AppError as AppError
from .errors import AppFileError as AppFileError
from .errors import ConnectionSizeError as ConnectionSizeError
from .errors import LibcError as LibcError
from .errors import PortValueError as PortValueError
from .errors import RtloopError as RtloopError
from .errors import TaskFailed as TaskFailed
from .runnable import Runnable as Runnable
from .runnable import TickInfo as TickInfo
from .summary import RunSummary as RunSummary
from .summary import TaskSummary as TaskSummary
from .timing import TaskTiming as TaskTiming

__version__ = "0.1.0"

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
    "TaskFailed",
    "TaskSummary",
    "TaskTiming",
    "TickInfo",
]
