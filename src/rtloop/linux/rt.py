"""Operating-system primitives for real-time tasks, through ctypes.

One thin layer mirrors the libc calls; every call goes through :func:`_check`, which
turns a failure into :class:`~rtloop.errors.LibcError` naming the call and errno.
Everything here is Linux-only.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import fcntl
import os
import platform
import resource
import signal
import time
from collections.abc import Callable, Set
from dataclasses import asdict, dataclass, field
from pathlib import Path

from rtloop.errors import LibcError
from rtloop.linux.machine import effective_capabilities, preemption_model

now_ns = time.monotonic_ns
"""CLOCK_MONOTONIC in nanoseconds: clock_gettime without a ctypes round-trip."""

_libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)

CLOCK_MONOTONIC = 1
TIMER_ABSTIME = 1
MCL_CURRENT = 1
MCL_FUTURE = 2
MCL_ONFAULT = 4
"""Linux 4.4+: lock each page when it is first touched, not every page of every mapping at once."""
LOCK_ALL_MEMORY_ENV = "RTLOOP_LOCK_ALL_MEMORY"
"""Set to 1 in a task's environment: mlockall without MCL_ONFAULT, every page of every mapping read in
and locked (as before MCL_ONFAULT): no first-call fault in any library's code, for ~35 MB more per
task with numpy; benchmarks/bench_locked_memory.py compares the two."""
EINTR = 4

POLICIES: dict[str, int] = {
    "fifo": os.SCHED_FIFO,
    "rr": os.SCHED_RR,
    "other": os.SCHED_OTHER,
    "deadline": 6,  # SCHED_DEADLINE, set through sched_setattr(2)
}
POLICY_NAMES = {number: name for name, number in POLICIES.items()}


class Timespec(ctypes.Structure):
    _fields_ = (("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long))


_clock_nanosleep = _libc.clock_nanosleep
_clock_nanosleep.argtypes = (
    ctypes.c_int,
    ctypes.c_int,
    ctypes.POINTER(Timespec),
    ctypes.POINTER(Timespec),
)
_clock_nanosleep.restype = ctypes.c_int
_mlockall = _libc.mlockall
_mlockall.argtypes = (ctypes.c_int,)
_mlockall.restype = ctypes.c_int


def _check(call: str, result: int, hint: str = "", *, returns_errno: bool = False) -> int:
    """Raise LibcError if a libc call failed. ``returns_errno``: the call returns the errno."""
    if returns_errno:
        if result != 0:
            raise LibcError(call, result, hint)
        return result
    if result == -1:
        raise LibcError(call, ctypes.get_errno(), hint)
    return result




def ioctl(fd: int, request: int, argument: bytearray | memoryview | ctypes.Structure, name: str) -> None:
    """``ioctl(fd, request, argument)``, the argument read and written in place; a failure raises
    :class:`~rtloop.errors.LibcError` naming the request (``ioctl(SPI_IOC_MESSAGE(1)) failed: …``).
    ``name`` is a literal at each call: nothing is built unless the call fails."""
    try:
        fcntl.ioctl(fd, request, argument, True)
    except OSError as error:
        raise LibcError(f"ioctl({name}) on fd {fd}", error.errno or 0) from None


class AbsoluteSleeper:
    """Sleeps until absolute CLOCK_MONOTONIC times, with a preallocated timespec.

    ``sleep_until`` allocates nothing, so it is safe inside the real-time loop.
    """

    def __init__(self) -> None:
        self._deadline = Timespec()
        self._deadline_ref = ctypes.byref(self._deadline)

    def sleep_until(self, deadline_ns: int) -> None:
        """Sleep to ``deadline_ns``, whatever signals arrive meanwhile."""
        while not self.sleep_or_signal(deadline_ns):
            pass  # a signal handler ran: sleep again to the same deadline

    def sleep_or_signal(self, deadline_ns: int) -> bool:
        """Sleep to ``deadline_ns``; False if a signal cut the sleep short (its handler has run then)."""
        deadline = self._deadline
        deadline.tv_sec, deadline.tv_nsec = divmod(deadline_ns, 1_000_000_000)
        result = _clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, self._deadline_ref, None)
        if result == EINTR:
            return False
        _check("clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)", result, returns_errno=True)
        return True


PR_SET_PDEATHSIG = 1
PR_SET_TIMERSLACK = 29


def set_timer_slack(slack_ns: int) -> None:
    """Let the kernel wake this thread at most ``slack_ns`` late (SCHED_OTHER's default is 50 µs)."""
    _check("prctl(PR_SET_TIMERSLACK)", _libc.prctl(PR_SET_TIMERSLACK, slack_ns, 0, 0, 0))


PR_SET_CHILD_SUBREAPER = 36
PR_GET_CHILD_SUBREAPER = 37


def die_with_parent(signum: int) -> None:
    """Ask the kernel to send ``signum`` to this process when its parent exits."""
    _check("prctl(PR_SET_PDEATHSIG)", _libc.prctl(PR_SET_PDEATHSIG, signum, 0, 0, 0))


def become_subreaper(on: bool = True) -> None:
    """prctl(PR_SET_CHILD_SUBREAPER): orphaned descendants are re-parented to this process, not init."""
    _check("prctl(PR_SET_CHILD_SUBREAPER)", _libc.prctl(PR_SET_CHILD_SUBREAPER, int(on), 0, 0, 0))


def is_subreaper() -> bool:
    """prctl(PR_GET_CHILD_SUBREAPER): whether this process is a subreaper (to give the state back)."""
    flag = ctypes.c_int(0)
    _check("prctl(PR_GET_CHILD_SUBREAPER)", _libc.prctl(PR_GET_CHILD_SUBREAPER, ctypes.byref(flag), 0, 0, 0))
    return bool(flag.value)


def child_pids(pid: int | None = None) -> set[int]:
    """Process ids whose parent is ``pid`` (default: this process), from /proc."""
    parent = os.getpid() if pid is None else pid
    children: set[int] = set()
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/stat", "rb") as file:
                fields = file.read().rsplit(b") ", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == parent and fields[0] not in (b"Z", b"X"):
            children.add(int(entry.name))
    return children


def end_strays(keep: Set[int] = frozenset(), rounds: int = 20,
               only: Callable[[int], bool] | None = None) -> list[int]:
    """SIGKILL every child of this process not in ``keep`` (and, given ``only``, for which it is
    true), and reap them; returns their ids.

    With :func:`become_subreaper`, the children include every orphaned descendant, so
    repeating until none is left ends whole trees, also processes that double-forked.
    """
    ended: list[int] = []
    for _ in range(rounds):
        strays = {pid for pid in child_pids() - set(keep) if only is None or only(pid)}
        if not strays:
            break
        for pid in strays:
            try:
                os.kill(pid, signal.SIGKILL)
                ended.append(pid)
            except ProcessLookupError:
                pass
        for pid in strays:
            try:
                os.waitpid(pid, 0)
            except ChildProcessError:
                pass
    return ended


def set_affinity(cpu: int | None) -> None:
    """Pin the calling process to one CPU (``None``: leave as is)."""
    if cpu is None:
        return
    try:
        os.sched_setaffinity(0, {cpu})
    except OSError as error:
        raise LibcError(
            f"sched_setaffinity(cpu={cpu})",
            error.errno or 0,
            f"this machine has CPUs {sorted(os.sched_getaffinity(0))}",
        ) from None


class _SchedAttr(ctypes.Structure):
    _fields_ = (
        ("size", ctypes.c_uint32),
        ("sched_policy", ctypes.c_uint32),
        ("sched_flags", ctypes.c_uint64),
        ("sched_nice", ctypes.c_int32),
        ("sched_priority", ctypes.c_uint32),
        ("sched_runtime", ctypes.c_uint64),
        ("sched_deadline", ctypes.c_uint64),
        ("sched_period", ctypes.c_uint64),
    )


_SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274, "armv7l": 380, "riscv64": 274}


def set_scheduler(
    policy: str, priority: int, *, runtime_ns: int = 0, period_ns: int = 0
) -> None:
    """Apply a scheduling policy to the calling process.

    ``policy`` is ``fifo``, ``rr``, ``other`` or ``deadline`` (SCHED_DEADLINE needs
    ``runtime_ns`` and ``period_ns``; deadline = period).
    """
    if policy == "deadline":
        number = _SYS_SCHED_SETATTR.get(platform.machine())
        if number is None:
            raise LibcError("sched_setattr(SCHED_DEADLINE)", 38, f"unknown on {platform.machine()}")
        attr = _SchedAttr(
            size=ctypes.sizeof(_SchedAttr),
            sched_policy=POLICIES["deadline"],
            sched_runtime=runtime_ns,
            sched_deadline=period_ns,
            sched_period=period_ns,
        )
        result = _libc.syscall(number, 0, ctypes.byref(attr), 0)
        _check(
            f"sched_setattr(SCHED_DEADLINE, runtime={runtime_ns} ns, period={period_ns} ns)",
            result,
            "needs root (CAP_SYS_NICE), a runtime ≤ period, and a task not pinned to one CPU",
        )
        return
    if policy not in POLICIES:
        raise ValueError(f"unknown scheduling policy {policy!r}; expected one of {list(POLICIES)}")
    try:
        os.sched_setscheduler(0, POLICIES[policy], os.sched_param(priority))
    except OSError as error:
        raise LibcError(
            f"sched_setscheduler(SCHED_{policy.upper()}, priority={priority})",
            error.errno or 0,
            "needs root, CAP_SYS_NICE or an RLIMIT_RTPRIO ≥ the priority (see `rtloop doctor`)",
        ) from None


def leave_realtime() -> bool:
    """Go back to SCHED_OTHER (always allowed): what runs after the loop must not delay real-time
    tasks sharing this core. False if the kernel refused all the same."""
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        return False
    return True


def limit_realtime_cpu(soft_s: float, hard_s: float) -> None:
    """Let the kernel end a real-time spin: RLIMIT_RTTIME counts the CPU time this thread uses
    at a real-time priority without blocking (each sleep resets it). At ``soft_s`` it sends
    SIGXCPU (once a second after), at ``hard_s`` SIGKILL. Unlike the supervisor's watchdog it
    needs no CPU time of its own: it works when busy tasks hold every core."""
    soft_us, hard_us = round(soft_s * 1e6), round(hard_s * 1e6)
    try:
        resource.setrlimit(resource.RLIMIT_RTTIME, (soft_us, hard_us))
    except (OSError, ValueError) as error:
        raise LibcError(f"setrlimit(RLIMIT_RTTIME, {soft_us} µs, {hard_us} µs)", getattr(error, "errno", 0) or 0,
                        "a hard limit above the current one needs root (CAP_SYS_RESOURCE)") from None


class _SignalEvent(ctypes.Structure):
    """struct sigevent for SIGEV_SIGNAL (Linux: 64 bytes)."""

    _fields_ = (("value", ctypes.c_void_p), ("signo", ctypes.c_int), ("notify", ctypes.c_int),
                ("rest", ctypes.c_int * 12))


class _TimerSpec(ctypes.Structure):
    _fields_ = (("interval", Timespec), ("value", Timespec))


def signal_self_after(signum: int, after_s: float) -> None:
    """Have the kernel send this process ``signum`` once, ``after_s`` from now (a POSIX timer on
    CLOCK_MONOTONIC): a deadline that needs no thread of this process to be running, and SIGKILL
    ends the process whatever it is stuck in."""
    event = _SignalEvent(None, signum, 0)  # SIGEV_SIGNAL
    timer = ctypes.c_void_p()
    _check("timer_create", _libc.timer_create(CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(timer)))
    whole_s = int(after_s)
    when = _TimerSpec(Timespec(0, 0), Timespec(whole_s, max(1, round((after_s - whole_s) * 1e9))))
    _check("timer_settime", _libc.timer_settime(timer, 0, ctypes.byref(when), None))


def lock_memory() -> bool:
    """mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT): no page faults from swapping in the loop.

    With MCL_ONFAULT the pages already resident are locked and the others when first touched, so
    the code of libraries the loop never runs (most of numpy and OpenBLAS) is not read in and
    pinned; the task then locks in full what its loop touches (linux/lean.py,
    ``lock_what_the_loop_touches``) before T0. Returns True when MCL_ONFAULT was in force; a
    kernel without it (EINVAL), or RTLOOP_LOCK_ALL_MEMORY=1, gets MCL_CURRENT | MCL_FUTURE, which
    faults in every mapping."""
    if os.environ.get(LOCK_ALL_MEMORY_ENV) == "1":
        pass
    elif _mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) == 0:
        return True
    elif ctypes.get_errno() != errno.EINVAL:
        _check("mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT)", -1,
               "needs root, CAP_IPC_LOCK or a large enough RLIMIT_MEMLOCK (see `rtloop doctor`)")
    _check(
        "mlockall(MCL_CURRENT|MCL_FUTURE)",
        _mlockall(MCL_CURRENT | MCL_FUTURE),
        "needs root, CAP_IPC_LOCK or a large enough RLIMIT_MEMLOCK (see `rtloop doctor`)",
    )
    return False


class CpuDmaLatency:
    """Hold ``/dev/cpu_dma_latency`` at 0 µs while open: keeps CPUs out of deep idle states.

    Waking a core from a deep C-state costs tens to hundreds of microseconds, which shows
    up as wake-up latency; cyclictest holds it at 0 too. The kernel honours the
    request only while the file stays open.
    """

    PATH = "/dev/cpu_dma_latency"

    def __init__(self) -> None:
        self.fd: int | None = None
        self.reason = ""

    def __enter__(self) -> CpuDmaLatency:
        try:
            self.fd = os.open(self.PATH, os.O_WRONLY)
            os.write(self.fd, (0).to_bytes(4, "little"))
        except OSError as error:
            self.reason = f"{self.PATH}: {error.strerror}"
            if self.fd is not None:
                os.close(self.fd)
            self.fd = None
        return self

    @property
    def held(self) -> bool:
        return self.fd is not None

    def __exit__(self, *exc: object) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def prefault_stack(size_bytes: int = 512 * 1024) -> None:
    """Touch stack-sized scratch memory once, so the loop's first cycles do not fault."""
    scratch = ctypes.create_string_buffer(size_bytes)
    ctypes.memset(scratch, 0, size_bytes)


@dataclass(frozen=True, slots=True)
class AppliedSettings:
    """What the task process really runs with, read back from the kernel."""

    policy: str
    """Scheduling policy now in force (``fifo``, ``rr``, ``other``, ``deadline``)."""
    priority: int
    """Real-time priority now in force (0 under ``other``)."""
    cpus: tuple[int, ...]
    """CPUs the process may run on."""
    memory_locked: bool
    """Whether mlockall succeeded."""
    rt: bool
    """True when a real-time policy is in force."""
    reasons: tuple[str, ...] = field(default=())
    """Why something asked for could not be applied (empty when everything was)."""


def read_back_settings(memory_locked: bool, reasons: tuple[str, ...]) -> AppliedSettings:
    policy_number = os.sched_getscheduler(0)
    policy = POLICY_NAMES.get(policy_number, str(policy_number))
    priority = os.sched_getparam(0).sched_priority
    return AppliedSettings(
        policy=policy,
        priority=priority,
        cpus=tuple(sorted(os.sched_getaffinity(0))),
        memory_locked=memory_locked,
        rt=policy in ("fifo", "rr", "deadline"),
        reasons=reasons,
    )


def apply_realtime(
    cpu: int | None, policy: str, priority: int, period_ns: int, runtime_ns: int = 0
) -> AppliedSettings:
    """Affinity, then priority, then memory locking; falls back instead of failing.

    Affinity comes first so that the process never runs at RT priority on a core it
    should not disturb. A refused policy leaves SCHED_OTHER in force and records why.
    """
    reasons: list[str] = []
    set_affinity(cpu)
    try:
        set_scheduler(policy, priority, runtime_ns=runtime_ns or period_ns // 2, period_ns=period_ns)
    except LibcError as error:
        reasons.append(str(error))
    memory_locked = True
    try:
        lock_memory()
    except LibcError as error:
        memory_locked = False
        reasons.append(str(error))
    prefault_stack()
    return read_back_settings(memory_locked, tuple(reasons))


@dataclass(frozen=True, slots=True)
class Capabilities:
    """Can this process run real-time tasks here, and how well? (a quick probe)"""

    may_use_rt: bool
    rt_reason: str
    max_rt_priority: int
    memlock_limit_bytes: int | None
    preemption_model: str
    isolated_cpus: tuple[int, ...]
    cpus: tuple[int, ...]
    kernel: str

    def to_json(self) -> dict[str, object]:
        return asdict(self)


CAP_IPC_LOCK = 14
CAP_SYS_NICE = 23


def parse_cpu_list(text: str) -> tuple[int, ...]:
    """Parse a kernel CPU list such as ``1,3-5`` into ``(1, 3, 4, 5)``."""
    cpus: list[int] = []
    for part in text.strip().split(","):
        if not part:
            continue
        if "-" in part:
            low, high = part.split("-")
            cpus.extend(range(int(low), int(high) + 1))
        else:
            cpus.append(int(part))
    return tuple(cpus)


def probe() -> Capabilities:
    """Answer: may this process use SCHED_FIFO and mlockall, and what is the kernel like?"""
    caps = effective_capabilities()
    rtprio_soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    memlock_soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    has_nice = bool(caps & (1 << CAP_SYS_NICE))
    if has_nice:
        may, reason, max_prio = True, "CAP_SYS_NICE", 99
    elif rtprio_soft == resource.RLIM_INFINITY or rtprio_soft > 0:
        may, reason = True, f"RLIMIT_RTPRIO={rtprio_soft}"
        max_prio = 99 if rtprio_soft == resource.RLIM_INFINITY else int(rtprio_soft)
    else:
        may, reason, max_prio = False, "no CAP_SYS_NICE and RLIMIT_RTPRIO is 0", 0
    try:
        isolated = parse_cpu_list(Path("/sys/devices/system/cpu/isolated").read_text())
    except OSError:
        isolated = ()
    has_ipc_lock = bool(caps & (1 << CAP_IPC_LOCK))
    memlock = None if has_ipc_lock or memlock_soft == resource.RLIM_INFINITY else int(memlock_soft)
    return Capabilities(
        may_use_rt=may,
        rt_reason=reason,
        max_rt_priority=max_prio,
        memlock_limit_bytes=memlock,
        preemption_model=preemption_model(),  # the doctor reads the same (linux/machine.py)
        isolated_cpus=isolated,
        cpus=tuple(sorted(os.sched_getaffinity(0))),
        kernel=platform.release(),
    )
