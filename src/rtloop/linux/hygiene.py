"""Process hygiene of a run: nothing a task starts outlives the app, and the caller gets back what it was.

The supervisor becomes the child subreaper for the run only (orphans of what the tasks start are
reparented to it), marks each task process's environment (inherited by whatever the task starts),
and at the end kills the children that carry this run's mark — never a child the caller started
itself. Also here: what /proc says of a task that stands still, and the supervisor's own
scheduling while busy real-time tasks would leave it only crumbs.
"""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterable, Iterator

from rtloop.linux import rt

TASK_MARK_ENV = "RTLOOP_TASK_OF_RUN"
"""Set in each task process's environment (and so in whatever it starts): what the cleanup may end."""
SUPERVISOR_PRIORITY = 1


@contextlib.contextmanager
def adopting_orphans(token: str) -> Iterator[None]:
    """For the run (``token``): become the subreaper of what the tasks start; on the way out end the
    marked children left (never one that existed before) and give the caller back its subreaper state."""
    try:
        was_subreaper = rt.is_subreaper()
    except OSError:
        was_subreaper = False
    with contextlib.suppress(OSError):  # an old kernel: task processes still end their own strays
        rt.become_subreaper()
    children_before = rt.child_pids()
    try:
        yield
    finally:
        end_marked_strays(token, keep=children_before | _multiprocessing_helpers())
        if not was_subreaper:  # a library's caller does not stay a subreaper after a run
            with contextlib.suppress(OSError):
                rt.become_subreaper(False)


def task_mark(token: str) -> str:
    return f"{os.getpid()}-{token}"


@contextlib.contextmanager
def marked_environment(token: str) -> Iterator[None]:
    """A process started in the block starts with this run's mark in its environment (its descendants inherit it)."""
    previous = os.environ.get(TASK_MARK_ENV)
    os.environ[TASK_MARK_ENV] = task_mark(token)
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop(TASK_MARK_ENV, None)
        else:
            os.environ[TASK_MARK_ENV] = previous


def server_mark() -> str:
    """The mark in the environment of the task server (runtime/task_start.py) this process starts.
    A task forked from it that forks without exec shows that environment in /proc, not the run's."""
    return f"{os.getpid()}-task-server"


def end_marked_strays(token: str, keep: set[int]) -> None:
    """SIGKILL what the tasks left running (orphans adopted here), never a child the caller started itself.

    Only children that carry this run's mark in their environment are ended: the task processes
    and whatever they started (a program started with a wiped environment escapes this and
    is reparented to init, as without rtloop). What carries the task server's mark counts too:
    the server itself is kept (it serves the next run), whatever else carries it came from a task.
    """
    marks = {f"{TASK_MARK_ENV}={mark}".encode() for mark in (task_mark(token), server_mark())}
    rt.end_strays(keep, only=lambda pid: _carries_mark(pid, marks))


def _multiprocessing_helpers() -> set[int]:
    """multiprocessing's helper processes (children of ours, started with the first task: they may carry
    a mark): the resource tracker and the task server (runtime/task_start.py), kept for the next run."""
    from multiprocessing import forkserver, resource_tracker

    pids = (getattr(resource_tracker._resource_tracker, "_pid", None),
            getattr(forkserver._forkserver, "_forkserver_pid", None))
    return {pid for pid in pids if pid}


def _carries_mark(pid: int, marks: set[bytes]) -> bool:
    try:
        with open(f"/proc/{pid}/environ", "rb") as file:
            return not marks.isdisjoint(file.read().split(b"\0"))
    except OSError:
        return False


@contextlib.contextmanager
def serving_below_real_time_tasks(all_tasks_above: bool, may_use_rt: bool) -> Iterator[None]:
    """Run this thread at SCHED_FIFO 1 in the block when every task is real-time above it.

    Busy real-time tasks leave the rest of the machine the crumbs (RT throttling: 5 %), shared
    with every SCHED_OTHER process: the supervisor then could not serve Ctrl-C, the watchdog or
    the recording. At the lowest real-time priority it runs whenever the tasks sleep, and a waking
    task preempts it at once, except inside a system call on a kernel that is not fully preemptible:
    hence :func:`away_from_task_cpus` too. Children (bridges) start as SCHED_OTHER (reset on fork).
    Not done when a task is SCHED_OTHER (the supervisor would starve it) or shares priority 1.
    """
    previous = None
    if may_use_rt and all_tasks_above:
        previous = os.sched_getscheduler(0), os.sched_getparam(0)
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(SUPERVISOR_PRIORITY))
        except OSError:
            previous = None
    try:
        yield
    finally:
        if previous is not None:
            os.sched_setscheduler(0, *previous)


@contextlib.contextmanager
def away_from_task_cpus(task_cpus: Iterable[int]) -> Iterator[frozenset[int]]:
    """Keep every thread of this process off the CPUs the tasks are pinned to, in the block (yields the
    CPUs it may use then; its own CPUs as before when no other CPU is left, or they cannot be changed).

    A task woken while the supervisor runs on its CPU waits for it: a kernel that is not fully
    preemptible (PREEMPT_NONE, VOLUNTARY, a PREEMPT_DYNAMIC "none") finishes the supervisor's system
    call first (its reads of /proc, its writes of the recording: tens of µs each), and the switch
    costs the task its caches. SCHED_FIFO 1 does not help there. cyclictest keeps its own main
    thread off the measured CPUs the same way (``--mainaffinity``). Enter it once the task processes
    and bridges have started: they inherit the mask at their start and keep the caller's CPUs. Each
    thread gets its own CPUs back on the way out.
    """
    try:
        before = {tid: os.sched_getaffinity(tid) for tid in _own_threads()}
    except OSError:
        before = {}
    allowed = frozenset(os.sched_getaffinity(0))
    away = allowed - set(task_cpus)
    if not before or not away or away == allowed:
        yield allowed
        return
    moved = {}
    for tid, cpus in before.items():
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            os.sched_setaffinity(tid, away)
            moved[tid] = cpus
    try:
        yield frozenset(away)
    finally:
        for tid, cpus in moved.items():
            with contextlib.suppress(OSError):
                os.sched_setaffinity(tid, cpus)


def _own_threads() -> list[int]:
    return [int(name) for name in os.listdir("/proc/self/task")]


def why_stuck(pid: int) -> str:
    """Why a task's cycles stand still, as /proc says: stopped (SIGSTOP, a debugger), or a stuck step."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            state = stat.read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        state = ""
    if state in ("T", "t"):
        return ("its process is stopped (state T: SIGSTOP, Ctrl-Z or a debugger), not running its step" if state == "T"
                else "its process is stopped by a debugger (state t)")
    return "the step is stuck (a blocking call or an endless loop)"


def describe_exit(exitcode: int) -> str:
    """A process's exit as words: ``killed by SIGKILL``, ``exit code 3``."""
    if exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"
