"""How the supervisor starts task processes: forked from a preloaded server, not a fresh interpreter each.

Started the "spawn" way, every task process of every run is a new interpreter that imports
``rtloop.runtime.task`` and numpy from scratch: ~0.9 s of CPU before its ``prerun``. Here one
server process per supervisor (multiprocessing's "forkserver") imports them once
(``runtime/task_server.py``), single-threaded, and forks each task process from that state,
which then starts in a few ms. The server is started with the caller's CPUs and scheduling,
single-threaded BLAS, and without the current folder on its ``sys.path``; it ignores SIGTERM and
SIGHUP (a process-group signal stops the tasks through the supervisor, not by ending the server
under them), and the app's own modules are never preloaded: a task loads them per run, after the
checks of docs/security.md, as before.

What a forked task would inherit from the server rather than from the supervisor is put back at
its start (:meth:`ChildStart.adopt`): the supervisor's environment as it is at this run (with
the run's mark, linux/hygiene.py) and its CPUs.

When the supervisor dies: the server ends (its "alive" pipe reads EOF once the supervisor's end
is closed; each task closes the copy the server hands it, first thing), and the kernel sends
each task its parent-death signal (``SUPERVISOR_GONE``, runtime/task.py): the loop stops in
order, its devices get their safe values. ``tests/test_task_start.py`` proves it.

Tasks are spawned as before when the environment asks BLAS for more than one thread (the server
would hold the pool's threads while it forks), when ``RTLOOP_TASK_START=spawn`` is set (the
reference of ``benchmarks/bench_task_start.py``), and in a process forked from one that had started
the server. The server is the standard library's one per process: a program that started it itself
with other modules to preload keeps its own (its tasks then import rtloop after the fork).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

START_ENV = "RTLOOP_TASK_START"
"""``spawn``: start every task process as a fresh interpreter (the old way, for comparison)."""
SERVER_ENV = "RTLOOP_TASK_SERVER"
"""Set only in the server's own environment at its start: its preload module takes its signals then."""
SERVER_MODULE = "rtloop.runtime.task_server"


@dataclass(frozen=True)
class ChildStart:
    """What a task process puts back at its start when it was forked from the server."""

    parent_pid: int
    """The task's parent when it starts: the server, or the supervisor when spawned."""
    environment: dict[str, str] | None = None
    """The supervisor's environment at this task's start (None: spawned, the exec gave it)."""
    cpus: frozenset[int] | None = None

    def adopt(self) -> None:
        """The supervisor's environment and CPUs, and the server's "alive" pipe closed here, so
        that the server ends with the supervisor, not with the last task."""
        if self.environment is None:
            return
        server = _stdlib_server()
        alive_fd = getattr(server, "_forkserver_alive_fd", None)
        if alive_fd is not None:
            with contextlib.suppress(OSError):
                os.close(alive_fd)
            server._forkserver_alive_fd = None
        os.environ.clear()
        os.environ.update(self.environment)
        if self.cpus:
            with contextlib.suppress(OSError):  # a CPU gone offline since: the task's own cpu= still applies
                os.sched_setaffinity(0, self.cpus)

    @property
    def forked(self) -> bool:
        return self.environment is not None


def forking_allowed() -> bool:
    """Whether task processes start from the server: not when asked to spawn, nor when BLAS may use
    threads (the server imports numpy, and a process that forks must hold no thread)."""
    from rtloop.linux.lean import SINGLE_THREADED

    if os.environ.get(START_ENV, "") == "spawn":
        return False
    return all(os.environ.get(name, "1") == "1" for name in SINGLE_THREADED)


def start_server() -> int | None:
    """Start the task server unless it runs (it imports the task's modules meanwhile); its pid, or
    None when tasks are spawned. Call it early, outside a run's mark: it lives as long as this process."""
    if not forking_allowed():
        return None
    from rtloop.linux.lean import single_threaded_children

    server = _stdlib_server()
    with single_threaded_children(), _server_environment():
        multiprocessing.get_context("forkserver").set_forkserver_preload([SERVER_MODULE])
        try:
            server.ensure_running()
        except ChildProcessError:  # a forked copy of a process that had started one: not ours to use
            return None
    return int(server._forkserver_pid)


def server_pid() -> int | None:
    """The running task server's pid (None: none started)."""
    pid = getattr(_stdlib_server(), "_forkserver_pid", None)
    return int(pid) if pid else None


def task_context() -> tuple[Any, int | None]:
    """The multiprocessing context to start task processes with, and the server's pid (None: spawned).
    Called before a run's mark is in the environment: the server outlives the run."""
    pid = start_server()
    return multiprocessing.get_context("spawn" if pid is None else "forkserver"), pid


def child_start(server: int | None) -> ChildStart:
    """What a task process started now adopts: call it where the task's environment is set (the run's mark)."""
    if server is None:
        return ChildStart(os.getpid())
    return ChildStart(server, dict(os.environ), frozenset(os.sched_getaffinity(0)))


def _stdlib_server() -> Any:
    """multiprocessing's one fork server of this process (its private fields: the pid, the "alive" pipe)."""
    from multiprocessing import forkserver

    return forkserver._forkserver


@contextlib.contextmanager
def _server_environment() -> Iterator[None]:
    """The server's start: its preload module knows it is in the server; the current folder is not
    put first on its ``sys.path`` (``python -c`` would), so nothing there shadows what it imports."""
    from rtloop.linux.hygiene import TASK_MARK_ENV, server_mark

    # the server's mark: a task's fork that never exec'd shows the server's environment in /proc
    added = {SERVER_ENV: "1", "PYTHONSAFEPATH": "1", TASK_MARK_ENV: server_mark()}
    previous = {name: os.environ.get(name) for name in added}
    os.environ.update(added)
    try:
        yield
    finally:
        for name, value in previous.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
