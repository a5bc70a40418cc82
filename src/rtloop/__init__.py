"""rtloop: real-time control loops in Python on Linux."""

from .errors import AppError as AppError
from .errors import AppFileError as AppFileError
from .errors import RtloopError as RtloopError
from .errors import TaskFailed as TaskFailed
from .runnable import Runnable as Runnable
from .runnable import TickInfo as TickInfo

__version__ = "0.1.0"
