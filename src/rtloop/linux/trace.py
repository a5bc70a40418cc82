"""``rtloop run --trace-misses``: the kernel's scheduler and IRQ trace events on the tasks' CPUs.

Where the kernel has tracefs (Debian's kernels, its -rt ones with the osnoise and timerlat
tracers too), a tracing instance of the run's own (``instances/rtloop-PID``: its own buffers,
leaving the machine's tracing alone) records, on the tasks' CPUs only, every context switch
(``sched:sched_switch``) and every IRQ and softirq handler (``irq:*``), stamped on
CLOCK_MONOTONIC (``trace_clock mono``). The supervisor reads the buffers between drains
(``poll``); for a late cycle, ``held`` says which threads and handlers had the CPU between its
release and its end, to the µs. The timerlat tracer (what ``rtla timerlat --auto-analysis``
uses) would add a FIFO-95 thread per CPU waking every period: a measurement that delays the
tasks it explains; the plain events need no thread of their own.

A kernel whose tracefs is not mounted (a VM's minimal init) gets a private mount for the run
(root only); a kernel without tracefs gets one line saying so, and the run goes on with rtloop's
own evidence.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import os
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

TRACEFS_PLACES = (Path("/sys/kernel/tracing"), Path("/sys/kernel/debug/tracing"))
EVENTS = ("sched/sched_switch", "sched/sched_wakeup", "irq/irq_handler_entry", "irq/irq_handler_exit",
          "irq/softirq_entry", "irq/softirq_exit")
EVENTS_KEPT = 200_000
"""Events kept per CPU (a 1 kHz task makes ~2000 context switches a second: ~1 min at least)."""
BUFFER_KB = 4096
_LINE = re.compile(r"^\s*(?P<comm>.+?)-(?P<pid>\d+)\s+\[(?P<cpu>\d+)\]\s+\S+\s+(?P<s>\d+)\.(?P<frac>\d+):\s+"
                   r"(?P<event>\w+):\s*(?P<rest>.*)$")
_SYSCALL = re.compile(r"NR (\d+)")
_BLOCK = re.compile(r"(?P<device>\d+,\d+) (?P<flags>\w+) (?:\d+ )?\(.*?\) (?P<sector>\d+) \+")
_FIELD = re.compile(r"(\w+)=(\S+)")


@dataclass(frozen=True)
class Event:
    at_ns: int
    kind: str
    """``switch`` (from ``prev`` to ``who``), ``wakeup`` (of ``who``), ``irq`` / ``softirq`` (``who`` its
    name), ``irq_end`` / ``softirq_end``; ``sleep_armed`` (a thread's sleep timer ``who`` started, to expire at
    ``expires_ns``), ``sleep_fired`` (timer ``who`` expired), ``syscall_exit`` (``who`` the system call's
    number), ``disk_issue`` / ``disk_done`` (a block request ``who``, ``device sector``, sent to / completed by
    the device; ``flags`` its kind: ``W`` write, ``R`` read, ``F`` a cache flush, ``S`` synchronous...)."""
    who: str
    priority: int = -1
    """The real-time priority of ``who`` for a switch or a wake-up (1-99; 0 for SCHED_OTHER), -1 for a handler."""
    prev: str = ""
    """A switch's outgoing thread."""
    prev_priority: int = -1
    context_pid: int = -1
    """The thread current on the CPU when the event was recorded (the line's ``comm-pid``)."""
    expires_ns: int = -1
    """A ``sleep_armed`` timer's expiry (CLOCK_MONOTONIC, the trace's clock)."""
    flags: str = ""
    """A disk request's kind (the kernel's ``rwbs``)."""
    inferred: bool = False
    """A ``switch`` the kernel did not trace, put back by :func:`with_untraced_switches`."""
    context_comm: str = field(default="", compare=False)
    """The name of ``context_pid`` (the line's ``comm``)."""


def find_tracefs() -> Path | None:
    """Where tracefs with the scheduler events is mounted, or None."""
    for place in TRACEFS_PLACES:
        if (place / "instances").is_dir() and (place / "events" / "sched" / "sched_switch").is_dir():
            return place
    return None


def kernel_has_tracefs() -> bool:
    try:
        return any(line.split()[-1] == "tracefs" for line in Path("/proc/filesystems").read_text().splitlines())
    except OSError:
        return False


def mount_tracefs() -> Path:
    """Mount tracefs in a private folder (a VM's minimal init mounts none; rtla and trace-cmd do the same):
    the caller unmounts it (``unmount``). Raises OSError (needs root)."""
    import tempfile

    place = Path(tempfile.mkdtemp(prefix="rtloop-tracefs-"))
    if _libc().mount(b"nodev", str(place).encode(), b"tracefs", 0, None) != 0:
        errno = ctypes.get_errno()
        place.rmdir()
        raise OSError(errno, f"mount -t tracefs: {os.strerror(errno)}")
    if not (place / "events" / "sched" / "sched_switch").is_dir():
        unmount(place)
        raise OSError(0, "this kernel's tracefs has no sched:sched_switch event")
    return place


def unmount(place: Path) -> None:
    _libc().umount2(str(place).encode(), 2)  # MNT_DETACH: gone even if a reader still holds a file
    with contextlib.suppress(OSError):
        place.rmdir()


def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(None, use_errno=True)


def availability() -> tuple[bool, str]:
    """Whether --trace-misses can work here, and if not the one line that says why."""
    if find_tracefs() is not None:
        return True, ""
    if not kernel_has_tracefs():
        return False, ("this kernel has no tracefs (not in /proc/filesystems; no osnoise/timerlat tracers "
                       "either): misses are explained from rtloop's own evidence")
    if os.geteuid() != 0:
        return False, ("tracefs is not mounted and only root may mount it: misses are explained from rtloop's "
                       "own evidence")
    return True, ""


class MissTracer:
    """A tracing instance on some CPUs, read between drains, asked about a window of one CPU."""

    def __init__(self, tracefs: Path, cpus: set[int]) -> None:
        self.root = tracefs / "instances" / f"rtloop-{os.getpid()}"
        self.cpus = sorted(cpus)
        self.events: dict[int, collections.deque[Event]] = {cpu: collections.deque(maxlen=EVENTS_KEPT)
                                                            for cpu in self.cpus}
        self.pipes: dict[int, int] = {}
        self.partial: dict[int, bytes] = dict.fromkeys(self.cpus, b"")
        self.mounted: Path | None = None
        """The private tracefs mount this tracer made (unmounted by ``close``)."""

    def arm(self) -> None:
        self.root.mkdir()
        try:
            (self.root / "trace_clock").write_text("mono")
            (self.root / "buffer_size_kb").write_text(str(BUFFER_KB))
            mask = sum(1 << cpu for cpu in self.cpus)
            (self.root / "tracing_cpumask").write_text(f"{mask:x}")
            for event in EVENTS:
                with contextlib.suppress(OSError):  # a kernel without softirq events still traces the rest
                    (self.root / "events" / event / "enable").write_text("1")
            for cpu in self.cpus:
                self.pipes[cpu] = os.open(self.root / "per_cpu" / f"cpu{cpu}" / "trace_pipe",
                                          os.O_RDONLY | os.O_NONBLOCK)
            (self.root / "tracing_on").write_text("1")
        except OSError:
            self.close()
            raise

    def poll(self) -> None:
        """Take what the buffers hold now (never waits)."""
        for cpu, fd in self.pipes.items():
            chunks = [self.partial[cpu]]
            while True:
                try:
                    chunk = os.read(fd, 1 << 16)
                except BlockingIOError:
                    break
                if not chunk:
                    break
                chunks.append(chunk)
            text = b"".join(chunks)
            lines = text.split(b"\n")
            self.partial[cpu] = lines.pop()
            for line in lines:
                event = parse(line.decode("utf-8", "replace"))
                if event is not None:
                    self.events[cpu].append(event)

    def held(self, cpu: int, from_ns: int, to_ns: int, own_pids: frozenset[int]) -> list[dict[str, object]]:
        """Who had ``cpu`` in [from_ns, to_ns]: threads (not ``own_pids``, not idle) and IRQ handlers,
        the longest first: ``{"who", "kind", "ran_ns", "priority"}``. A switch the kernel did not trace
        is put back by :func:`with_untraced_switches` (the one rule, shared with the wake-up bench)."""
        events = self.events.get(cpu)
        if not events:
            return []
        ran: dict[tuple[str, object], int] = collections.Counter()
        labels: dict[int, tuple[str, int]] = {}  # pid -> the fullest label seen, its priority

        def credit(kind: str, key: object, start_ns: int, end_ns: int) -> None:
            overlap = min(end_ns, to_ns) - max(start_ns, from_ns)
            if overlap > 0:
                ran[(kind, key)] += overlap

        running_pid, since = 0, from_ns
        entered: dict[str, int] = {}
        names: dict[str, str] = {}
        for event in with_untraced_switches(events):
            if event.at_ns > to_ns:
                break
            if event.kind == "switch":
                prev_pid, next_pid = pid_of(event.prev), pid_of(event.who)
                if labels.get(prev_pid, ("", -1))[1] < 0:  # its switch-in's label wins, unless put back
                    labels[prev_pid] = (event.prev, event.prev_priority)
                labels[next_pid] = (event.who, event.priority)
                if running_pid > 0:
                    credit("thread", running_pid, since, event.at_ns)
                running_pid, since = next_pid, event.at_ns
            elif event.kind in ("irq", "softirq"):  # keyed by "IRQ 24": the exit event has no name
                entered[event.kind + event.who.split(" (")[0]] = event.at_ns
                names[event.kind + event.who.split(" (")[0]] = event.who
            elif event.kind in ("irq_end", "softirq_end"):
                key = event.kind[:-4] + event.who
                start = entered.pop(key, None)
                if start is not None:
                    credit(event.kind[:-4], names.get(key, event.who), start, event.at_ns)
        if running_pid > 0:
            credit("thread", running_pid, since, to_ns)
        found: list[tuple[int, str, str, int]] = []
        for (kind, holder), ran_ns in ran.items():
            if kind == "thread":
                if not isinstance(holder, int) or holder in own_pids:
                    continue
                who, priority = labels.get(holder, (f"pid {holder}", -1))
                if who.startswith("swapper/"):
                    continue
                found.append((ran_ns, who, kind, priority))
            else:
                found.append((ran_ns, str(holder), kind, -1))
        found.sort(key=lambda item: -item[0])
        return [{"who": who, "kind": kind, "ran_ns": ran_ns, "priority": priority}
                for ran_ns, who, kind, priority in found]

    def close(self) -> None:
        for fd in self.pipes.values():
            os.close(fd)
        self.pipes.clear()
        with contextlib.suppress(OSError):
            (self.root / "tracing_on").write_text("0")
        with contextlib.suppress(OSError):
            self.root.rmdir()  # removes the instance and its buffers
        if self.mounted is not None:
            unmount(self.mounted)
            self.mounted = None


def with_untraced_switches(events: Iterable[Event]) -> Iterator[Event]:
    """One CPU's events in order, with the switches to a thread the kernel did not trace put back
    (``switch`` events with ``inferred=True``).

    Some kernels leave the switch out of idle untraced (seen on a 6.18 VM kernel: every
    ``swapper → thread`` switch missing, every ``thread → swapper`` one there). An event recorded in
    the context of a thread other than the one last switched in (idle's, pid 0, never counts) says
    that thread was switched in: it ran from the first sign of it on this CPU since the last switch,
    its wake-up here or that event, whichever came first. A thread's own switch out is such an event
    too (the kernel records it in the outgoing thread's context): a thread never seen before it is
    put back as running from that instant, i.e. for no time at all.
    """
    running_pid, running, running_priority = -1, "", -1
    labels: dict[int, tuple[str, int]] = {}  # pid -> label, priority (from the switches and wake-ups seen)
    first_sign: dict[int, int] = {}  # pid -> its wake-up on this CPU since the last switch
    for event in events:
        if event.kind == "wakeup":
            first_sign.setdefault(pid_of(event.who), event.at_ns)
        pid = event.context_pid
        if pid > 0 and pid != running_pid:
            label, priority = labels.get(pid, (f"{event.context_comm or '?'} (pid {pid})", -1))
            yield Event(min(first_sign.get(pid, event.at_ns), event.at_ns), "switch", label, priority, running,
                        running_priority, pid, inferred=True, context_comm=event.context_comm)
            running_pid, running, running_priority = pid, label, priority
            first_sign.clear()
        if event.kind in ("switch", "wakeup"):
            labels[pid_of(event.who)] = (event.who, event.priority)
        if event.kind == "switch":
            if labels.get(pid_of(event.prev), ("", -1))[1] < 0:
                labels[pid_of(event.prev)] = (event.prev, event.prev_priority)
            running_pid, running, running_priority = pid_of(event.who), event.who, event.priority
            first_sign.clear()
        yield event


def pid_of(who: str) -> int:
    """The pid in a thread's label (``name (pid N, ...)``), -1 if none."""
    match = re.search(r"pid (\d+)", who)
    return int(match.group(1)) if match else -1


def _thread(name: str, pid: str, prio_text: str) -> tuple[str, int]:
    """A thread's label (``name (pid N, FIFO/RR P)``) and real-time priority from a kernel prio (0-139)."""
    prio = int(prio_text)
    if prio < 100:
        return f"{name} (pid {pid}, FIFO/RR {99 - prio})", 99 - prio
    return f"{name} (pid {pid}, other)", 0


def _between(text: str, start: str, end: str) -> str:
    """The text between two field names (a thread's comm may hold spaces)."""
    begin = text.find(start) + len(start)
    return text[begin:text.find(end, begin)]


def parse(line: str) -> Event | None:
    """One line of a trace pipe (the default text format), or None for anything else."""
    match = _LINE.match(line)
    if match is None:
        return None
    at_ns = int(match["s"]) * 1_000_000_000 + int(match["frac"].ljust(9, "0")[:9])
    context_pid, comm = int(match["pid"]), match["comm"].strip()
    rest = match["rest"]
    fields = dict(_FIELD.findall(rest))
    event = match["event"]
    if event == "sched_switch":
        who, priority = _thread(_between(rest, "next_comm=", " next_pid="), fields.get("next_pid", "?"),
                                fields.get("next_prio", "120"))
        prev, prev_priority = _thread(_between(rest, "prev_comm=", " prev_pid="), fields.get("prev_pid", "?"),
                                      fields.get("prev_prio", "120"))
        return Event(at_ns, "switch", who, priority, prev, prev_priority, context_pid, context_comm=comm)
    if event == "sched_wakeup":
        if fields.get("target_cpu", "").lstrip("0") != match["cpu"].lstrip("0"):
            return None  # woken onto another CPU: not this CPU's story
        who, priority = _thread(_between(rest, "comm=", " pid="), fields.get("pid", "?"), fields.get("prio", "120"))
        return Event(at_ns, "wakeup", who, priority, context_pid=context_pid, context_comm=comm)
    if event == "irq_handler_entry":
        return Event(at_ns, "irq", f"IRQ {fields.get('irq', '?')} ({fields.get('name', '?')})",
                     context_pid=context_pid, context_comm=comm)
    if event == "irq_handler_exit":
        return Event(at_ns, "irq_end", f"IRQ {fields.get('irq', '?')}", context_pid=context_pid, context_comm=comm)
    if event in ("softirq_entry", "softirq_exit"):
        action = fields.get("action", "?").strip("[]")
        return Event(at_ns, "softirq" if event == "softirq_entry" else "softirq_end", f"softirq {action}",
                     context_pid=context_pid, context_comm=comm)
    if event == "hrtimer_start" and fields.get("function") == "hrtimer_wakeup":  # a sleeping thread's timer
        return Event(at_ns, "sleep_armed", fields.get("hrtimer", "?"), context_pid=context_pid,
                     expires_ns=int(fields.get("softexpires") or fields.get("expires") or "-1"), context_comm=comm)
    if event == "hrtimer_expire_entry" and fields.get("function", "").startswith("hrtimer_wakeup"):
        return Event(at_ns, "sleep_fired", fields.get("hrtimer", "?"), context_pid=context_pid, context_comm=comm)
    if event in ("block_rq_issue", "block_rq_complete") and (request := _BLOCK.match(rest)):
        return Event(at_ns, "disk_issue" if event == "block_rq_issue" else "disk_done",
                     f"{request['device']} {request['sector']}", context_pid=context_pid, flags=request["flags"],
                     context_comm=comm)
    if event == "sys_exit" and (number := _SYSCALL.search(rest)):
        return Event(at_ns, "syscall_exit", number[1], context_pid=context_pid, context_comm=comm)
    return None


def open_tracer(cpus: set[int]) -> tuple[MissTracer | None, str]:
    """An armed tracer on ``cpus``, or None and the one line that says why not."""
    usable, why = availability()
    if not usable:
        return None, why
    tracefs, mounted = find_tracefs(), None
    try:
        if tracefs is None:
            tracefs = mounted = mount_tracefs()
        tracer = MissTracer(tracefs, cpus)
        tracer.mounted = mounted
        tracer.arm()
    except OSError as error:
        if mounted is not None:
            unmount(mounted)
        return None, f"tracefs refused the tracing instance ({error}): misses are explained from rtloop's own evidence"
    return tracer, ""
