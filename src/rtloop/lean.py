"""Keep task processes lean: one thread each.

A BLAS or OpenMP worker pool in a real-time process is a priority-inversion trap: the
loop's thread waits on workers that run at whatever priority they inherited, and the
pool's stacks and buffers are locked into memory by ``mlockall``. numpy's OpenBLAS reads
its thread count once, when numpy is first imported, so the limit has to be in the
environment a task process starts with.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

SINGLE_THREADED = {
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "BLIS_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}


@contextmanager
def single_threaded_children() -> Iterator[None]:
    """Processes started inside inherit single-threaded BLAS/OpenMP (unless the user chose a count)."""
    added = [name for name in SINGLE_THREADED if name not in os.environ]
    os.environ.update({name: SINGLE_THREADED[name] for name in added})
    try:
        yield
    finally:
        for name in added:
            os.environ.pop(name, None)
