"""Keep task processes lean: one thread each, and only what the loop needs locked in memory.

A BLAS or OpenMP worker pool in a real-time process is a priority-inversion trap: the
loop's thread waits on workers that run at whatever priority they inherited, and the
pool's stacks and buffers are locked into memory by ``mlockall``. numpy's OpenBLAS reads
its thread count once, when numpy is first imported, so the limit has to be in the
environment a task process starts with.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

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


# --- memory locking --------------------------------------------------------------------
# mlockall(MCL_CURRENT|MCL_FUTURE) locks every mapping of the process, whether the loop can
# touch it or not. Two kinds it provably never needs (VmLck counts mappings, not pages):

_libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
_libc.munlock.argtypes = (ctypes.c_void_p, ctypes.c_size_t)
_libc.mlock.argtypes = (ctypes.c_void_p, ctypes.c_size_t)
_libc.madvise.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
MADV_DONTNEED = 4


@dataclass(frozen=True, slots=True)
class Mapping:
    """One line of ``/proc/self/maps``."""

    start: int
    end: int
    permissions: str
    path: str

    @property
    def size_bytes(self) -> int:
        return self.end - self.start


def mappings() -> list[Mapping]:
    found = []
    for line in Path("/proc/self/maps").read_text().splitlines():
        fields = line.split(maxsplit=5)
        start, end = (int(address, 16) for address in fields[0].split("-"))
        found.append(Mapping(start, end, fields[1], fields[5] if len(fields) > 5 else ""))
    return found


def openblas_work_buffer(found: list[Mapping]) -> Mapping | None:
    """Make OpenBLAS keep a single work buffer, and return its mapping (None: not OpenBLAS, or threaded).

    OpenBLAS reserves a 32 MB buffer (x86_64) for its thread pool when it loads, and the first
    level-3 product (``A @ B``; ``A @ x`` packs on the stack) on the calling thread maps
    another one: under mlockall that faulted in 32 MB inside the loop (14.6 ms and 8,192
    faults for a 3×3 product, measured). With one thread the pool never runs; shutting it
    down puts its buffer back in OpenBLAS's allocator, which then hands it to the caller:
    one buffer, mapped before the loop. Taking it and giving it back tells us where it is.
    """
    paths = {m.path for m in found if "openblas" in Path(m.path).name}
    for path in paths:
        try:
            library = ctypes.CDLL(path)
            allocate, free = library.blas_memory_alloc, library.blas_memory_free
            shutdown, threads = library.blas_thread_shutdown_, _openblas_threads(library)
        except (OSError, AttributeError):
            continue
        if threads != 1:
            continue  # the user chose a thread pool: leave its memory as it is
        allocate.restype, allocate.argtypes = ctypes.c_void_p, (ctypes.c_int,)
        free.restype, free.argtypes = None, (ctypes.c_void_p,)
        shutdown()
        address = allocate(0)
        if not address:
            continue
        free(address)
        for mapping in mappings():
            if mapping.start <= address < mapping.end and not mapping.path and "rw" in mapping.permissions:
                return mapping
    return None


def _openblas_threads(library: ctypes.CDLL) -> int:
    for name in ("openblas_get_num_threads", "openblas_get_num_threads64_", "scipy_openblas_get_num_threads64_"):
        function = getattr(library, name, None)
        if function is not None:
            function.restype = ctypes.c_int
            return int(function())
    raise AttributeError("openblas_get_num_threads")


@dataclass(frozen=True, slots=True)
class Unlocked:
    """What :func:`unlock_what_the_loop_never_needs` released from the lock."""

    guard_bytes: int
    """PROT_NONE reservations (gaps between a library's segments): a touch would be a crash."""
    blas_buffer_bytes: int
    """OpenBLAS's work buffer (0 when kept locked or not found)."""
    blas_buffer: Mapping | None = None
    """Where that buffer is, when it was unlocked (:func:`lock_what_the_loop_touches` leaves it out)."""
    blas_in_the_loop: bool = False
    """The task said it multiplies matrices in its loop (``lock_blas_buffer``): BLAS code locked in full too."""


def unlock_what_the_loop_never_needs(lock_blas_buffer: bool) -> Unlocked:
    """After mlockall: unlock PROT_NONE reservations and, unless asked to keep it, the BLAS buffer.

    OpenBLAS is first made to keep one work buffer (see :func:`openblas_work_buffer`). That
    buffer is also given back (MADV_DONTNEED: mlockall had faulted in all 32 MB).
    A step that multiplies matrices then faults in, once, the pages it packs into (two 4 KiB
    pages for 3×3 @ 3×3, measured) and they stay; with swap enabled they are not pinned.
    """
    found = mappings()
    guard_bytes = 0
    for mapping in found:
        if mapping.permissions.startswith("---") and _libc.munlock(mapping.start, mapping.size_bytes) == 0:
            guard_bytes += mapping.size_bytes
    blas_bytes = 0
    buffer = openblas_work_buffer(found)
    if buffer is not None and not lock_blas_buffer and _libc.munlock(buffer.start, buffer.size_bytes) == 0:
        _libc.madvise(buffer.start, buffer.size_bytes, MADV_DONTNEED)
        blas_bytes = buffer.size_bytes
    return Unlocked(guard_bytes, blas_bytes, buffer if blas_bytes else None, lock_blas_buffer)


# Under mlockall(MCL_ONFAULT) (rt.lock_memory) a page is locked when first touched: a page the
# loop first touches after T0 is a page fault inside a cycle (the timing ring takes one every
# 128 cycles, measured before this). So, the last thing before T0, the task locks in full, with
# mlock(2) (which faults every page in), all the memory its loop may touch: every writable
# mapping (heap, stack, Python's arenas, numpy arrays, the shared segments: timing ring, record
# queues, channels) and all of the interpreter and rtloop's own code. What stays locked only as
# far as it was touched is the code and read-only data of other libraries (numpy, OpenBLAS,
# libgfortran...): what imports and prerun ran is locked; a function a step calls for the first
# time inside the loop takes one minor fault per new page, once.
LOOP_CODE = ("libpython", "libc.so", "libc-", "libm.so", "libm-", "ld-linux", "/rtloop/")
"""Mappings whose code the loop always runs: the interpreter, libc, libm, the loader, rtloop's own."""
BLAS_CODE = ("openblas", "_multiarray_umath", "libgfortran", "libquadmath")
"""And of a task that multiplies matrices in its loop (``lock_blas_buffer``): numpy's core and its BLAS
(a first 3×3 product in the loop faulted in 3 pages of their code)."""


def the_loop_touches(mapping: Mapping, interpreter: str, blas: bool = False) -> bool:
    if mapping.permissions.startswith("---"):
        return False  # a reservation: a touch would crash
    if mapping.path.startswith("[") and mapping.path not in ("[heap]", "[stack]"):
        return False  # [vdso], [vvar], [vsyscall]: the kernel's own, never swapped
    if "w" in mapping.permissions[:2]:
        return True
    code = LOOP_CODE + BLAS_CODE if blas else LOOP_CODE
    return mapping.path == interpreter or any(part in mapping.path for part in code)


@dataclass(frozen=True, slots=True)
class Touched:
    """What :func:`lock_what_the_loop_touches` locked in full."""

    locked_bytes: int
    failed: tuple[str, ...] = ()
    """Mappings mlock refused (address range and errno), for a note."""


def lock_what_the_loop_touches(unlocked: Unlocked | None) -> Touched:
    """Fault in and lock every page the loop may touch (see above); call it the last thing before T0,
    after prerun and everything the task maps (segments, devices, arrays), with the memory locked."""
    skip = unlocked.blas_buffer if unlocked is not None else None
    blas = unlocked is not None and unlocked.blas_in_the_loop
    interpreter = os.path.realpath("/proc/self/exe")
    locked = 0
    failed = []
    for mapping in mappings():
        if (skip is not None and mapping.start == skip.start) or not the_loop_touches(mapping, interpreter, blas):
            continue
        if _libc.mlock(mapping.start, mapping.size_bytes) == 0:
            locked += mapping.size_bytes
        else:
            failed.append(f"{mapping.start:x}-{mapping.end:x} {mapping.path}: {os.strerror(ctypes.get_errno())}")
    return Touched(locked, tuple(failed))


# A task process forked from the task server (runtime/task_start.py) shares the server's pages, but
# not the page-table entries of its file mappings (the kernel leaves those to fault in again): the
# library code and read-only data the server's imports ran are present in the server, not in the
# task. A spawned task ran its imports itself, so MCL_ONFAULT had locked those pages; a forked one
# would fault each in the first time its loop runs it (one fault in the first cycle, measured).
# So it touches the pages the server holds (those its pagemap says are present) once before T0:
# under mlockall(MCL_ONFAULT) each is locked as it faults in, as the spawned task's imports did
# (an mlock(2) of each run of pages would split the mappings into thousands of pieces).
PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")
PRESENT = 1 << 63


def lock_what_the_server_ran(server_pid: int) -> Touched:
    """Fault in (and so lock, under MCL_ONFAULT) the pages of this process's read-only file mappings that
    are present in the task server (``server_pid``, the process this one was forked from), where the
    mapping is the same in both."""
    interpreter = os.path.realpath("/proc/self/exe")
    try:
        with open(f"/proc/{server_pid}/maps") as maps:
            theirs = {tuple(int(address, 16) for address in line.split(maxsplit=1)[0].split("-")) for line in maps}
        pagemap = open(f"/proc/{server_pid}/pagemap", "rb", buffering=0)  # noqa: SIM115  (closed below)
    except OSError as error:
        return Touched(0, (f"the task server's page map ({error.strerror})",))
    locked = 0
    with pagemap:
        for mapping in mappings():
            if (not mapping.path.startswith("/") or "w" in mapping.permissions[:2] or mapping.permissions[0] != "r"
                    or the_loop_touches(mapping, interpreter) or (mapping.start, mapping.end) not in theirs):
                continue  # anonymous or writable (locked in full already), a reservation, or not the server's
            pagemap.seek(mapping.start // PAGE_BYTES * 8)
            entries = memoryview(pagemap.read(mapping.size_bytes // PAGE_BYTES * 8)).cast("Q")
            for start, end in _present_runs(entries, mapping.start):
                pages = memoryview((ctypes.c_char * (end - start)).from_address(start)).cast("B")
                bytes(pages[::PAGE_BYTES])  # one byte read of each page: a fault that locks it
                locked += end - start
    return Touched(locked)


def _present_runs(entries: memoryview, first_address: int) -> list[tuple[int, int]]:
    """The address ranges of consecutive present pages, from pagemap entries starting at ``first_address``."""
    runs: list[tuple[int, int]] = []
    start = None
    for index, entry in enumerate(entries):
        if entry & PRESENT:
            if start is None:
                start = index
        elif start is not None:
            runs.append((first_address + start * PAGE_BYTES, first_address + index * PAGE_BYTES))
            start = None
    if start is not None:
        runs.append((first_address + start * PAGE_BYTES, first_address + len(entries) * PAGE_BYTES))
    return runs
