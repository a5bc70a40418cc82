"""What running apps are doing now, for ``rtloop top`` (``cli/top.py``; ``cli/top_view.py`` draws it).

Apps are found through their registry files (``/dev/shm/rtloop-<app>-<pid>-<token>-
registry.json``); an app whose supervisor is gone is ignored. Each task's status block
is mapped and only ever read. What the status block does not hold comes from /proc:
scheduling as the kernel sees it, CPU time, context switches and page faults.

Two numbers are top's own, because no task keeps them: the *latency max* is the
highest LATENCY_LAST value top saw while polling (a sample, not the true maximum:
that is in ``summary.json`` after the run), and *%CPU* is measured between refreshes.
"""

from __future__ import annotations

import json
import os
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rtloop.ipc.ports import Refusal, scan_registries, unreachable_app
from rtloop.ipc.segments import SHM_DIR, Segment
from rtloop.ipc.status import STATUS_WORDS, StatusWord, TaskState, WordBlock

POLL_HZ = 50
"""How often top reads LATENCY_LAST between refreshes (to keep its running maximum)."""
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
SCHED_NAMES = {0: "other", 1: "fifo", 2: "rr", 3: "batch", 5: "idle", 6: "deadline"}
LATENCY_MAX_NOTE = ("lat max: highest latency top saw polling the status block at "
                    f"{POLL_HZ} Hz since it started (tasks do not keep a maximum); the true one is in summary.json")


@dataclass(frozen=True)
class Registry:
    """One running app, as its registry file describes it."""

    app: str
    pid: int
    """The supervisor's process id."""
    tasks: dict[str, str]
    """Task name → its status segment name."""
    path: Path
    uid: int = -1
    """The supervisor's uid: every segment of the app must be owned by it."""
    summary: str | None = None
    """The run's live summary.json (rewritten every few seconds), if the registry names it."""


def find_apps(app: str | None = None, shm_dir: Path = SHM_DIR) -> list[Registry]:
    """Running apps (supervisor alive), optionally only those named ``app``."""
    return find_apps_and_refusals(app, shm_dir)[0]


def find_apps_and_refusals(app: str | None = None, shm_dir: Path = SHM_DIR) -> tuple[list[Registry], list[Refusal]]:
    """Running apps as :func:`find_apps`, and the registries (of ``app``) refused: another user's
    app among them is not "no running app" (``rtloop port`` says the same, :func:`unreachable_app`)."""
    found, refused = scan_registries(shm_dir)
    registries = sorted(
        (Registry(entry.name, entry.pid, dict(entry.registry.get("tasks", {})), entry.path, entry.uid,
                  entry.registry.get("summary"))
         for entry in found if app is None or entry.name == app),
        key=lambda registry: registry.path,
    )
    return registries, [refusal for refusal in refused if app is None or refusal.app == app]


def unreachable_notes(refused: list[Refusal]) -> list[str]:
    """One line per app that runs as another user (its registry not readable): run top as that user."""
    names = sorted({refusal.app for refusal in refused if refusal.denied_by_owner is not None})
    return [str(unreachable_app(name, refused, "top")) for name in names]


# --- /proc ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ProcStat:
    """What /proc says about one task process."""

    policy: str
    rt_priority: int
    last_cpu: int
    affinity: tuple[int, ...]
    cpu_ticks: int
    """utime + stime, in clock ticks."""
    start_ticks: int
    minflt: int
    majflt: int
    nonvoluntary_ctxt_switches: int | None


def read_proc(pid: int) -> ProcStat | None:
    """/proc/PID/stat and /proc/PID/status of ``pid`` (None if it is gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        status = Path(f"/proc/{pid}/status").read_text()
        affinity = tuple(sorted(os.sched_getaffinity(pid)))
    except (OSError, ProcessLookupError):
        return None
    # Fields after the command name (which may contain spaces); rest[0] is field 3, state.
    rest = stat[stat.rindex(")") + 2 :].split()
    nvcsw = None
    for line in status.splitlines():
        if line.startswith("nonvoluntary_ctxt_switches:"):
            nvcsw = int(line.split()[1])
    return ProcStat(
        policy=SCHED_NAMES.get(int(rest[38]), rest[38]),
        rt_priority=int(rest[37]),
        last_cpu=int(rest[36]),
        affinity=affinity,
        cpu_ticks=int(rest[11]) + int(rest[12]),
        start_ticks=int(rest[19]),
        minflt=int(rest[7]),
        majflt=int(rest[9]),
        nonvoluntary_ctxt_switches=nvcsw,
    )


def _uptime_s() -> float:
    return float(Path("/proc/uptime").read_text().split()[0])


# --- the monitor ----------------------------------------------------------------------
@dataclass(frozen=True)
class TaskView:
    """One row of the table."""

    name: str
    state: str
    pid: int
    cpu: str
    sched: str
    cycles: int
    cycles_per_s: float | None
    overruns: int
    deadline_misses: int
    stale_reads: int
    latency_now_ns: int
    latency_max_ns: int
    exec_last_ns: int
    cpu_percent: float | None
    nonvoluntary_ctxt_switches: int | None
    minflt: int | None
    majflt: int | None
    gc_collections: str = "n/a"
    """Not visible from outside the task process (rtloop disables gc in the loop)."""


@dataclass(frozen=True)
class AppView:
    """One running app."""

    app: str
    pid: int
    tasks: list[TaskView] = field(default_factory=list)
    summary_line: str = ""
    """What the live summary.json says (true latency maxima, recording), '' if unreadable."""


@dataclass
class _Tracked:
    status: WordBlock
    segment: Segment
    latency_max_ns: int = 0
    last_cycles: int | None = None
    last_cpu: tuple[int, float] | None = None  # (cpu ticks, monotonic s)
    last_time_s: float | None = None


class Monitor:
    """Keeps status blocks mapped and the numbers top computes itself across refreshes."""

    def __init__(self, app: str | None = None, shm_dir: Path = SHM_DIR) -> None:
        self.app = app
        self.shm_dir = shm_dir
        self.tracked: dict[str, _Tracked] = {}
        self.registries: list[Registry] = []
        self.refused: list[Refusal] = []
        """Registries (of ``app``) found but refused at the last refresh: another user's among them."""

    def _attach(self, segment_name: str, uid: int = -1) -> _Tracked | None:
        tracked = self.tracked.get(segment_name)
        if tracked is None:
            try:
                # Segment maps read-write; top only ever reads these words.
                segment = Segment.attach(segment_name, owner_uid=uid if uid >= 0 else None)
            except (FileNotFoundError, ValueError, OSError):
                return None
            tracked = self.tracked[segment_name] = _Tracked(WordBlock(segment, 0, STATUS_WORDS), segment)
        return tracked

    def refresh_apps(self) -> list[Registry]:
        self.registries, self.refused = find_apps_and_refusals(self.app, self.shm_dir)
        alive = {seg for registry in self.registries for seg in registry.tasks.values()}
        for name in [n for n in self.tracked if n not in alive]:
            del self.tracked[name]  # the mapping is released with the objects
        return self.registries

    def poll(self) -> None:
        """Read every task's latest latency (cheap; called between refreshes)."""
        for registry in self.registries:
            for segment_name in registry.tasks.values():
                tracked = self._attach(segment_name, registry.uid)
                if tracked is not None:
                    latency = tracked.status[StatusWord.LATENCY_LAST_NS]
                    tracked.latency_max_ns = max(tracked.latency_max_ns, latency)

    def snapshot(self) -> list[AppView]:
        """Every running app and its tasks, now."""
        self.refresh_apps()
        self.poll()
        views = []
        for registry in self.registries:
            view = AppView(registry.app, registry.pid,
                           summary_line=live_summary_line(registry.summary, registry.uid))
            for task, segment_name in registry.tasks.items():
                tracked = self._attach(segment_name, registry.uid)
                if tracked is not None:
                    view.tasks.append(self._task_view(task, tracked))
            views.append(view)
        return views

    def _task_view(self, name: str, tracked: _Tracked) -> TaskView:
        status = tracked.status
        now_s = time.monotonic()
        latency_now_ns = status[StatusWord.LATENCY_LAST_NS]  # read once: the task writes it every cycle
        tracked.latency_max_ns = max(tracked.latency_max_ns, latency_now_ns)
        state_value = status[StatusWord.STATE]
        state = TaskState(state_value).name if state_value in TaskState._value2member_map_ else str(state_value)
        pid = status[StatusWord.PID]
        ran = state_value in (TaskState.RUNNING, TaskState.POSTRUN, TaskState.STOPPED, TaskState.FAILED) and status[
            StatusWord.EXEC_LAST_NS] > 0
        cycles = status[StatusWord.CYCLE] + 1 if ran else 0
        rate = None
        if tracked.last_cycles is not None and tracked.last_time_s is not None and now_s > tracked.last_time_s:
            rate = (cycles - tracked.last_cycles) / (now_s - tracked.last_time_s)
        tracked.last_cycles, tracked.last_time_s = cycles, now_s
        proc = read_proc(pid) if pid > 0 else None
        cpu_percent = None
        pinned = status[StatusWord.CPU]
        cpu = "any" if pinned < 0 else str(pinned)
        sched = "-"
        if proc is not None:
            if tracked.last_cpu is not None and now_s > tracked.last_cpu[1]:
                used_s = (proc.cpu_ticks - tracked.last_cpu[0]) / CLOCK_TICKS
                cpu_percent = 100.0 * used_s / (now_s - tracked.last_cpu[1])
            else:  # first look: average over the process's life
                alive_s = _uptime_s() - proc.start_ticks / CLOCK_TICKS
                cpu_percent = 100.0 * proc.cpu_ticks / CLOCK_TICKS / alive_s if alive_s > 0 else None
            tracked.last_cpu = (proc.cpu_ticks, now_s)
            cpu = f"{cpu} (on {proc.last_cpu})"
            sched = f"{proc.policy}:{proc.rt_priority}" if proc.rt_priority else proc.policy
        return TaskView(
            name=name, state=state, pid=pid, cpu=cpu, sched=sched, cycles=cycles, cycles_per_s=rate,
            overruns=status[StatusWord.OVERRUNS], deadline_misses=status[StatusWord.DEADLINE_MISSES],
            stale_reads=status[StatusWord.STALE_READS], latency_now_ns=latency_now_ns,
            latency_max_ns=tracked.latency_max_ns, exec_last_ns=status[StatusWord.EXEC_LAST_NS],
            cpu_percent=cpu_percent,
            nonvoluntary_ctxt_switches=proc.nonvoluntary_ctxt_switches if proc else None,
            minflt=proc.minflt if proc else None, majflt=proc.majflt if proc else None,
        )

    def poll_for(self, seconds: float) -> None:
        """Poll at POLL_HZ for ``seconds`` (keeps the running latency maximum)."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            time.sleep(min(left, 1 / POLL_HZ))
            self.poll()


MAX_SUMMARY_BYTES = 1 << 22
"""A live summary.json larger than this is not read (a run's is a few kB per task)."""


def live_summary_line(path: str | None, app_uid: int | None = None) -> str:
    """One line from a running app's summary.json: per task p99/max latency, and the recording.

    The path comes from the app's registry, which another user wrote when root runs ``rtloop
    top``: only a regular file of bounded size is read (a FIFO would block top, /dev/zero
    would fill its memory), not through a link, and only one the app's user owns (``app_uid``;
    root's runs give theirs to the user who ran sudo): never a file of root's or another user's
    that the registry names. Anything else gives no line."""
    if not path or not isinstance(path, str):
        return ""
    try:
        summary, modified_s = _read_bounded_regular_file(path, app_uid)
        age_s = time.time() - modified_s
        parts = []
        for name, task in summary["tasks"].items():
            latency = task["latency_ns"]
            if latency.get("max") is not None:
                parts.append(f"{name} p99 {latency['p99'] / 1e3:,.1f} max {latency['max'] / 1e3:,.1f} µs")
        recording = summary.get("recording", {})
        stopped = recording.get("stopped")
        keep_s = recording.get("keep_s")
        parts.append(f"recording: {stopped}" if stopped else
                     f"recording: the last {keep_s:g} s kept" if keep_s else "recording: everything kept")
        return f"summary.json ({age_s:.0f} s old): " + "; ".join(parts)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return ""


def _read_bounded_regular_file(path: str, owner_uid: int | None = None) -> tuple[Any, float]:
    """The JSON in ``path`` and its modification time; ValueError unless a regular file of at most
    MAX_SUMMARY_BYTES (opened without blocking: a FIFO never holds top up, nor following a link)
    owned by ``owner_uid`` (None, or 0: root's run may have given it to the sudo user: any owner)."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | os.O_CLOEXEC)
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode) or info.st_size > MAX_SUMMARY_BYTES:
            raise ValueError(f"{path}: not a summary.json")
        if owner_uid not in (None, 0, info.st_uid):
            raise ValueError(f"{path}: owned by uid {info.st_uid}, not by the app's uid {owner_uid}")
        with os.fdopen(fd, "rb", closefd=False) as file:
            data = file.read(MAX_SUMMARY_BYTES + 1)
    finally:
        os.close(fd)
    if len(data) > MAX_SUMMARY_BYTES:
        raise ValueError(f"{path}: not a summary.json")
    try:
        return json.loads(data), info.st_mtime
    except RecursionError:
        raise ValueError(f"{path}: nested too deeply; not a summary.json") from None
