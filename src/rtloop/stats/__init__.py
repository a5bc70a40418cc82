"""Timing statistics: samples of a run's cycles into the figures ``summary.json`` and the report show.

:mod:`timing` holds the definitions (latency, jitter, misses) as pure functions over every
sample; :mod:`timing_stream` computes the same record from batches in fixed memory
(:mod:`histogram`), as a days-long run needs, with those same functions: ``summary.json``
(the recorder streams), ``rtloop bench`` and the report's figures all count a cycle alike.
Nothing here does I/O.
"""

DEFAULT_TRIM = 20
"""Cycles left out at each end of a task's statistics (the thesis's choice). Here, not in
:mod:`timing`, so the command line gives it as a default without importing numpy."""
