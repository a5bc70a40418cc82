"""Shared memory between task processes and the supervisor: segments, fences, rings.

Segments are files in ``/dev/shm`` created with mode 0600 and ``O_EXCL`` and named
``rtloop-<app>-<supervisor pid>-<run token>-<what>``, so a later run can recognise
and remove what a dead run left behind (:func:`remove_stale_segments`).

Trust: ``/dev/shm`` is writable by every user, so a name found there proves nothing.
Names must match :data:`SEGMENT_NAME` (no path separators); files are opened relative
to the directory, never through a symbolic link, must be regular files, and an
attach can demand an owner (``owner_uid``): a segment of another user is refused
with a :class:`SegmentRefused` that says whose it is.

Memory ordering uses ``atomic_thread_fence`` from libatomic, so a reader on another
core of an aarch64 machine never sees a counter before the data it announces. On
x86-64 (total store order) a missing libatomic falls back to no fence; on other
architectures it is an error.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import gc
import mmap
import os
import platform
import re
import stat
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

from rtloop.errors import RtloopError
from rtloop.text import shorten

SHM_DIR = Path("/dev/shm")
SEGMENT_PREFIX = "rtloop-"
SEGMENT_NAME = re.compile(r"rtloop-([A-Za-z0-9_]{1,40})-(\d{1,10})-([0-9a-f]{8})-([A-Za-z0-9_.]{1,80})")
"""``rtloop-<app>-<supervisor pid>-<token>-<what>``: the only names rtloop creates or opens."""
_SEQ_CST = 5  # __ATOMIC_SEQ_CST


def _load_fence() -> tuple[Callable[[int], object] | None, str]:
    path = ctypes.util.find_library("atomic") or "libatomic.so.1"
    try:
        fence = ctypes.CDLL(path).atomic_thread_fence
    except (OSError, AttributeError):
        if platform.machine() in ("x86_64", "AMD64"):
            return None, "libatomic not found: no fences (safe on x86-64, whose stores are ordered)"
        raise RuntimeError(
            "libatomic.so.1 is needed for memory fences on "
            f"{platform.machine()}; install it (Debian: apt-get install libatomic1)"
        ) from None
    fence.argtypes = (ctypes.c_int,)
    fence.restype = None
    return fence, "atomic_thread_fence from libatomic"


_fence_function, FENCE_KIND = _load_fence()


def fence() -> None:
    """A full memory barrier (sequentially consistent)."""
    if _fence_function is not None:
        _fence_function(_SEQ_CST)


def _sanitize(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.]", "_", text)[:40]


def new_run_token() -> str:
    return os.urandom(4).hex()  # not `secrets`: it drags hashlib and libcrypto into every task process


class SegmentRefused(RtloopError, PermissionError):
    """A segment or registry was not believed: bad name, a link, not a file, or another user's."""


class SegmentDenied(SegmentRefused):
    """The kernel refused to open a segment or registry: it belongs to ``owner_uid`` (None: unknown)."""

    def __init__(self, message: str, owner_uid: int | None) -> None:
        super().__init__(message)
        self.owner_uid = owner_uid

    def __reduce__(self) -> tuple[type, tuple[str, int | None]]:
        return type(self), (str(self), self.owner_uid)


def check_segment_name(name: str) -> re.Match[str]:
    """The parts of a valid segment name; refuses anything else (e.g. ``../etc/passwd``)."""
    match = SEGMENT_NAME.fullmatch(name) if isinstance(name, str) else None
    if match is None or ".." in name:
        raise SegmentRefused(f"{shorten(name)} is not an rtloop segment name (expected {SEGMENT_NAME.pattern})")
    return match


def open_in_shm(name: str, flags: int, *, mode: int = 0o600, owner_uid: int | None = None,
                shm_dir: Path = SHM_DIR) -> int:
    """Open ``shm_dir/name`` without following links; a regular file owned by ``owner_uid``.

    Returns the file descriptor. Raises :class:`SegmentRefused` for a bad name, a link,
    a non-file or a file of another owner; ``FileNotFoundError`` if it is not there.
    """
    check_segment_name(name)
    directory = os.open(shm_dir, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        try:
            fd = os.open(name, flags | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK, mode, dir_fd=directory)
        except OSError as error:
            if error.errno == errno.ELOOP:  # the name is a symbolic link
                raise SegmentRefused(f"{shm_dir}/{name} is a symbolic link; rtloop never follows one") from None
            if isinstance(error, PermissionError):
                owner = _owner(name, directory)
                owned = f"owned by uid {owner}" if owner is not None else "owner unknown"
                raise SegmentDenied(f"{shm_dir}/{name}: permission denied ({owned}; you are uid {os.geteuid()})",
                                    owner) from None
            raise
    finally:
        os.close(directory)
    info = os.fstat(fd)
    problem = ""
    if not stat.S_ISREG(info.st_mode):
        problem = "is not a regular file"
    elif owner_uid is not None and info.st_uid != owner_uid:
        problem = f"is owned by uid {info.st_uid}, not by the app's uid {owner_uid}"
    if problem:
        os.close(fd)
        raise SegmentRefused(f"{shm_dir}/{name} {problem}; not used")
    return fd


def _owner(name: str, directory: int) -> int | None:
    try:
        return os.stat(name, dir_fd=directory, follow_symlinks=False).st_uid
    except OSError:
        return None


class Segment:
    """A named shared-memory file mapped into this process."""

    def __init__(self, name: str, size_bytes: int, *, create: bool, owner_uid: int | None = None) -> None:
        self.name = name
        self.path = SHM_DIR / name
        flags = os.O_RDWR | (os.O_CREAT | os.O_EXCL if create else 0)
        fd = open_in_shm(name, flags, owner_uid=owner_uid)
        try:
            if create:
                os.ftruncate(fd, size_bytes)
            else:
                size_bytes = os.fstat(fd).st_size
                if size_bytes <= 0:
                    raise SegmentRefused(f"{self.path} is empty; not an rtloop segment")
            self.size_bytes = size_bytes
            # The run's creator (the supervisor) maps every page now: it touches them all as the rings
            # and queues fill, and its resident size would otherwise grow for a minute or more (JIWY:
            # +3.7 MiB in 90 s) with no memory taken from the machine (the tasks lock these pages).
            populate = getattr(mmap, "MAP_POPULATE", 0) if create else 0
            self._map = mmap.mmap(fd, size_bytes, flags=mmap.MAP_SHARED | populate)
        except BaseException:
            os.close(fd)
            raise
        self.fd = fd
        """Kept open: ``flock`` on it serialises port writers and readers (no reopening by path)."""
        self.buffer = memoryview(self._map)

    @classmethod
    def create(cls, app: str, owner_pid: int, token: str, what: str, size_bytes: int) -> Segment:
        name = f"{SEGMENT_PREFIX}{_sanitize(app)}-{owner_pid}-{token}-{_sanitize(what)}"
        return cls(name, max(size_bytes, 8), create=True)

    @classmethod
    def attach(cls, name: str, owner_uid: int | None = None) -> Segment:
        """Map an existing segment; with ``owner_uid``, only if that user owns it."""
        return cls(name, 0, create=False, owner_uid=owner_uid)

    def array(self, dtype: npt.DTypeLike, count: int, offset_bytes: int = 0) -> np.ndarray:
        return np.frombuffer(self._map, dtype=dtype, count=count, offset=offset_bytes)

    def close(self) -> bool:
        """Close the descriptor and unmap; returns whether the mapping is gone (views of it may
        still be alive: then it goes when they do, with the mapping's own descriptor)."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
        try:
            self.buffer.release()
            self._map.close()
        except BufferError:
            return False
        return True

    def unlink(self) -> None:
        unlink_in_shm(self.name)


def close_segments(segments: list[Segment]) -> list[Segment]:
    """Close every segment of a process that goes on (a library's caller, the simulator); returns
    those whose mapping is still held by a view somewhere (their descriptors are closed).

    Views that sit in reference cycles (a closure, an exception's frames) go only with a garbage
    collection: one is run when a mapping is still held, so no run leaves mappings behind.
    """
    busy = [segment for segment in segments if not segment.close()]
    if busy:
        gc.collect()
        busy = [segment for segment in busy if not segment.close()]
    return busy


def unlink_in_shm(name: str, shm_dir: Path = SHM_DIR) -> None:
    """Remove ``shm_dir/name`` (a valid segment name; a link is removed, never followed)."""
    check_segment_name(name)
    directory = os.open(shm_dir, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        os.unlink(name, dir_fd=directory)
    except FileNotFoundError:
        pass
    finally:
        os.close(directory)


def process_uid(pid: int) -> int | None:
    """Effective uid of a live process (None if it is gone): whose files it creates."""
    try:
        with open(f"/proc/{pid}/status") as file:
            for line in file:
                if line.startswith("Uid:"):
                    return int(line.split()[2])
    except (OSError, ValueError, IndexError):
        return None
    return None


def process_start_ticks(pid: int) -> int | None:
    """When a live process started, in clock ticks since boot (None if it is gone): with its pid,
    it names the process for good, where a pid alone may be reused after the process ends."""
    try:
        with open(f"/proc/{pid}/stat") as file:
            return int(file.read().rsplit(") ", 1)[1].split()[19])
    except (OSError, IndexError, ValueError):
        return None


def pid_alive(pid: int) -> bool:
    """Whether a process with this id is running (it may belong to another user; a zombie is not)."""
    if pid <= 0:  # kill(0, ...) would ask about our own process group
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    try:
        with open(f"/proc/{pid}/stat") as file:
            return file.read().rsplit(") ", 1)[1][:1] not in ("Z", "X")
    except (OSError, IndexError):
        return True


def remove_stale_segments() -> list[str]:
    """Remove this user's segments whose supervisor process no longer exists.

    Only files owned by the calling user are touched (another user's leftovers are
    theirs to clean), and only names rtloop itself creates.
    """
    removed: list[str] = []
    me = os.geteuid()
    for path in SHM_DIR.glob(f"{SEGMENT_PREFIX}*"):
        match = SEGMENT_NAME.fullmatch(path.name)
        if not match or pid_alive(int(match.group(2))):
            continue
        try:
            if path.lstat().st_uid != me:
                continue
            unlink_in_shm(path.name)
            removed.append(path.name)
        except OSError:
            pass
    return removed
