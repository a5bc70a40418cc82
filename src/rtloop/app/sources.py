"""What an app was made of, by content: a digest of every file it loaded.

A run records them (``replay.json``'s ``files``): the app file, each module loaded by file for
it (the runnables', the twins', and the modules those load in turn), each model (an FMU, a
20-sim folder) and each profile fed to a port. ``rtloop replay`` runs today's files; when one
changed since the run it says so first, and a difference it finds is then put down to that
change, not to a model that is not deterministic.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import stat
from collections.abc import Iterator, Mapping
from pathlib import Path

_COLLECTING: list[dict[str, str]] = []
"""The collections open now (:func:`collecting`), innermost last."""

CHUNK_BYTES = 1 << 20


def digest_of_bytes(data: bytes) -> str:
    return "sha256:" + hashlib.sha256(data).hexdigest()


def file_digest(path: str | Path) -> str | None:
    """The digest of a file, or of a folder (each file's path in it and bytes, in sorted order);
    None when it is gone or cannot be read."""
    path = Path(path)
    try:
        if path.is_dir():
            total = hashlib.sha256()
            for child in sorted(path.rglob("*")):
                if child.is_file() and not child.is_symlink():
                    total.update(str(child.relative_to(path)).encode() + b"\0")
                    total.update(_hash_file(child))
            return "sha256:" + total.hexdigest()
        return "sha256:" + _hash_file(path).hex()
    except OSError:
        return None


def _hash_file(path: Path) -> bytes:
    digest = hashlib.sha256()
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # a FIFO put in a file's place: no wait
    with open(fd, "rb") as stream:
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # /dev/zero would be read forever
            raise OSError(errno.EINVAL, "not a regular file", str(path))
        while chunk := stream.read(CHUNK_BYTES):
            digest.update(chunk)
    return digest.digest()


@contextlib.contextmanager
def collecting() -> Iterator[dict[str, str]]:
    """Collect the files noted while the block runs (path → digest); collections nest."""
    files: dict[str, str] = {}
    _COLLECTING.append(files)
    try:
        yield files
    finally:
        del _COLLECTING[next(i for i, open_now in enumerate(_COLLECTING) if open_now is files)]


def note(files: Mapping[str, str]) -> None:
    """Add ``files`` to every open collection."""
    for collection in _COLLECTING:
        collection.update(files)


def changes_since(recorded: Mapping[str, str]) -> list[str]:
    """One phrase per recorded file whose content is not what it was (or that is gone)."""
    changes = []
    for path, digest in recorded.items():
        now = file_digest(path)
        if now is None:
            changes.append(f"{path} is gone")
        elif now != digest:
            try:
                modified = f", modified {_local_time(os.stat(path).st_mtime)}"
            except OSError:
                modified = ""
            changes.append(f"{path} changed since the run{modified}")
    return changes


def _local_time(seconds: float) -> str:
    import time

    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(seconds))
