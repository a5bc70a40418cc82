"""rtloop: real-time control loops in Python on Linux.

Write a :class:`Runnable`, add it to an :class:`App` as a periodic task, wire tasks
with ``app.connect``, reach them from non-real-time code through ports, then
``rtloop.run(app, ...)`` (real time) or ``rtloop.simulate(app, ...)`` (offline, lock-step).
"""

import importlib
import sys
from typing import TYPE_CHECKING, Any

# The errors and the version import nothing: they stay eager, so ``except rtloop.TaskFailed``
# never imports anything.
from rtloop.errors import AppError as AppError
from rtloop.errors import AppFileError as AppFileError
from rtloop.errors import ConnectionSizeError as ConnectionSizeError
from rtloop.errors import LibcError as LibcError
from rtloop.errors import PortValueError as PortValueError
from rtloop.errors import RtloopError as RtloopError
from rtloop.errors import StopRequested as StopRequested
from rtloop.errors import TaskFailed as TaskFailed
from rtloop.version import __version__ as __version__

if TYPE_CHECKING:
    from rtloop.app.builder import App as App
    from rtloop.app.specs import SignalRef as SignalRef
    from rtloop.record.load import RunData as RunData
    from rtloop.record.load import load as load
    from rtloop.record.summary import RunSummary as RunSummary
    from rtloop.record.summary import TaskSummary as TaskSummary
    from rtloop.runnable import Runnable as Runnable
    from rtloop.runnable import TickInfo as TickInfo
    from rtloop.runtime.simulate import simulate as simulate
    from rtloop.runtime.supervisor import run as run
    from rtloop.stats.timing import TaskTiming as TaskTiming
    from rtloop.switching import Controllers as Controllers
    from rtloop.toolbox.sweep import sweep as sweep

# Every other name is imported on first use (PEP 562), not here, for two reasons:
# - every ``rtloop`` command imports this package first: eager imports would make
#   ``rtloop --help`` or ``rtloop port write`` load numpy and the app description;
# - every task process imports it too (it unpickles rtloop.runtime.task): the supervisor,
#   the recorder and their dependencies would be loaded, and locked into memory by mlockall,
#   in each of them.
# A task process has imported the modules of App, Runnable and TickInfo before its loop
# starts (runtime/task.py imports them at its top), so a first ``rtloop.Runnable`` inside a
# step finds its module in sys.modules: a dictionary look-up, never a file read.
_LAZY = {
    "App": "rtloop.app.builder",
    "SignalRef": "rtloop.app.specs",
    "RunData": "rtloop.record.load",
    "load": "rtloop.record.load",
    "RunSummary": "rtloop.record.summary",
    "TaskSummary": "rtloop.record.summary",
    "Runnable": "rtloop.runnable",
    "TickInfo": "rtloop.runnable",
    "simulate": "rtloop.runtime.simulate",
    "run": "rtloop.runtime.supervisor",
    "sweep": "rtloop.toolbox.sweep",
    "TaskTiming": "rtloop.stats.timing",
    "Controllers": "rtloop.switching",
}


def __getattr__(name: str) -> Any:
    module_name = _LAZY.get(name)
    if module_name is None:
        raise AttributeError(f"module 'rtloop' has no attribute {name!r}")
    module = sys.modules.get(module_name) or importlib.import_module(module_name)
    value = getattr(module, name)
    globals()[name] = value  # the next access is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})


__all__ = [
    "App",
    "AppError",
    "AppFileError",
    "ConnectionSizeError",
    "Controllers",
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
