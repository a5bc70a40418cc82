"""The machine's available memory and a process's resident and locked size, from /proc (None where unreadable);
giving the heap's free pages back to the kernel."""

from __future__ import annotations

import ctypes
from pathlib import Path
from typing import Any

PROC = Path("/proc")


def _kib_field(path: Path, field: str) -> int | None:
    """``field:  1234 kB`` of a /proc status-like file, in bytes."""
    try:
        text = path.read_text()
    except OSError:
        return None
    for line in text.splitlines():
        name, _, rest = line.partition(":")
        if name == field:
            parts = rest.split()
            return int(parts[0]) * 1024 if parts and parts[0].isdigit() else None
    return None


def available_bytes(proc: Path = PROC) -> int | None:
    """``MemAvailable``: what new processes can take without swapping (the kernel's estimate)."""
    return _kib_field(proc / "meminfo", "MemAvailable")


def resident_bytes(pid: int | str = "self", proc: Path = PROC) -> int | None:
    """``VmRSS`` of a process: the memory it holds now."""
    return _kib_field(proc / str(pid) / "status", "VmRSS")


_TRIM: list[Any] = []  # [malloc_trim] once looked up, [None] where the C library has none (musl)


def give_back_free_heap() -> bool:
    """glibc's ``malloc_trim(0)``: free pages anywhere in the heap go back to the kernel.

    The supervisor drains batches of different sizes into numpy arrays and bytes: freed, their
    pages stay with the process (glibc keeps them for reuse, in several arenas when threads
    allocate), and its resident size creeps up for minutes (a 95 s soak: +2.7 MB). Called at every
    summary rewrite (every 2 s) it keeps the resident size to what is in use; it costs about a
    millisecond, outside any real-time task. Returns whether memory was given back."""
    if not _TRIM:
        function = getattr(ctypes.CDLL(None), "malloc_trim", None)  # the C library this process runs on
        if function is not None:
            function.argtypes, function.restype = [ctypes.c_size_t], ctypes.c_int
        _TRIM.append(function)
    function = _TRIM[0]
    return bool(function(0)) if function is not None else False


def locked_bytes(pid: int | str = "self", proc: Path = PROC) -> int | None:
    """Memory a process holds locked in RAM: the resident pages (``Rss``) of its locked mappings
    (``lo`` in ``VmFlags`` of ``/proc/PID/smaps``), pages shared with other processes counted whole.

    Not ``VmLck`` of ``status``: that is the size of every locked mapping, pages touched or not, so
    under ``mlockall(MCL_ONFAULT)`` it counts library code never read in. Nor ``Locked`` of
    ``smaps_rollup``: that is a proportional share (a page shared by 3 processes counts a third), so it
    falls as more task processes share the same libraries."""
    try:
        text = (proc / str(pid) / "smaps").read_text()
    except OSError:
        return None
    total_kib = rss_kib = 0
    for line in text.splitlines():
        if line.startswith("Rss:"):
            rss_kib = int(line.split()[1])
        elif line.startswith("VmFlags:") and "lo" in line.split()[1:]:
            total_kib += rss_kib
    return total_kib * 1024
