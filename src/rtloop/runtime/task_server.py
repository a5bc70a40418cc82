"""Imported once by the task server (runtime/task_start.py) before it forks task processes.

What every task process imports anyway (its entry point, numpy, the hot path, the devices' host
side), so each forked task finds it loaded. Nothing of the supervisor, the recorder or the app's
own code: a forked task maps, and mlockall locks, what the server holds.
"""

from __future__ import annotations

import os
import signal

import rtloop.runtime.task  # noqa: F401  (what is preloaded)
from rtloop.runtime.task_start import SERVER_ENV

if os.environ.pop(SERVER_ENV, None):  # in the server itself (a process-group signal must not end it
    # under running tasks: they would take its death for the supervisor's); Ctrl-C it ignores already
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
