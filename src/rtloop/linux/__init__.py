"""Linux primitives for real-time processes: scheduling, memory locking, clocks, subreapers.

:mod:`rt` is the thin checked layer over libc (every call raises
:class:`~rtloop.errors.LibcError` naming itself); :mod:`lean` keeps task processes to one
thread and only the memory the loop needs locked; :mod:`machine` reads what the kernel, the limits
and the processes say, below a ``root`` (``/`` live, a fake tree in tests), for the engine's probe
and the doctor (:mod:`rtloop.toolbox.doctor`) alike. Nothing here knows of apps or runs.
"""
