"""The machine's available memory and a process's resident size, from /proc (None where unreadable)."""

from __future__ import annotations

from pathlib import Path

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
