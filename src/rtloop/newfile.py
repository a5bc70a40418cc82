"""Files rtloop writes under a name it chose (a temporary before a rename, a reserve): made new,
never opened through what already has the name. A link planted there by another user would
otherwise be followed, and a process running as root would write onto the file it points to."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

NEW_FILE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC


def open_new(path: Path, mode: int = 0o644) -> int:
    """A descriptor of a new, empty file at ``path``: whatever had the name is removed first (a
    link itself, never what it points to), and the open follows no link and takes no existing file."""
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    return os.open(path, NEW_FILE_FLAGS, mode)


def write_new(path: Path, data: bytes, *, sync: bool = False) -> None:
    """Write ``data`` into a new file at ``path`` (see :func:`open_new`)."""
    fd = open_new(path)
    with open(fd, "wb") as file:
        file.write(data)
        if sync:
            file.flush()
            os.fsync(file.fileno())
