"""The run summary: frozen records whose JSON form is ``summary.json``."""

from __future__ import annotations

import contextlib
import errno
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypedDict

from rtloop.newfile import open_new, write_new
from rtloop.stats.timing import TaskTiming
from rtloop.text import counted


@dataclass(frozen=True, slots=True)
class TaskSummary:
    """How one task ran: where, with which scheduling, and how well it kept time."""

    period_ns: int
    """Nominal period."""
    priority: int
    """Real-time priority in force while it ran (0 if not real-time)."""
    cpu: int | None
    """CPU it was pinned to (None: not pinned)."""
    policy: str
    """Scheduling policy in force (fifo, rr, deadline or other)."""
    rt: bool
    """Whether a real-time policy was in force."""
    rt_reason: str
    """Why not real-time, or what could not be applied ('' when everything was)."""
    memory_locked: bool
    """Whether mlockall succeeded."""
    timing: TaskTiming
    """Timing statistics."""
    stale_reads: int
    """Stale connection reads: reads of a connection that found an older value than the tick was
    entitled to (its writer was late). ``stale_connection_reads`` in summary.json; a device's stale
    reads are the other kind (:meth:`RunSummary.stale_device_reads`)."""
    timing_samples_dropped: int
    """Timing samples lost because the supervisor did not drain fast enough."""
    misses_in_a_row_max: int = 0
    """The longest run of consecutive deadline misses (what ``max_consecutive_misses`` limits)."""
    input_names: tuple[str, ...] | None = None
    """Names of u[0], u[1], ... if the runnable gives them (a model's .info file, say)."""
    output_names: tuple[str, ...] | None = None
    """Names of y[0], y[1], ... if the runnable gives them."""
    host_exec_ns: dict[str, float] | None = None
    """Simulation only: what ``step`` cost on the host (count, mean, max), not real time."""
    nonfinite_values: int = 0
    """NaN or ±inf outputs headed across a connection (a fault unless the connection allows them)."""
    nonfinite_first: str = ""
    """The first of them: ``plant.y[1] (speed) at cycle 304`` ('' when none)."""
    resident_bytes: dict[str, int] | None = None
    """Run only: the task process's resident memory at the supervisor's samples (first, last, max)."""
    locked_bytes: int | None = None
    """Run only, memory locked: the resident pages of the task process's locked mappings, once all the
    memory its loop may touch was locked, before T0 (not VmLck: see rtloop.linux.memory.locked_bytes)."""
    input_limits: dict[str, dict[str, int]] | None = None
    """Inputs fed by a connection with ``min``/``max``/``rate_per_s`` whose guard acted: per input,
    ``clamped_cycles`` and ``rate_limited_cycles`` (``{}``: guarded, never acted; None: none guarded)."""

    def to_json(self) -> dict[str, Any]:
        timing = self.timing.to_json()
        return {
            "period_ns": self.period_ns,
            "priority": self.priority,
            "cpu": self.cpu,
            "policy": self.policy,
            "rt": self.rt,
            "rt_reason": self.rt_reason,
            "memory_locked": self.memory_locked,
            **{k: v for k, v in timing.items() if k != "period_ns"},
            "stale_connection_reads": self.stale_reads,
            "timing_samples_dropped": self.timing_samples_dropped,
            "misses_in_a_row_max": self.misses_in_a_row_max,
            "nonfinite_values": self.nonfinite_values,
            "nonfinite_first": self.nonfinite_first,
            "input_names": list(self.input_names) if self.input_names else None,
            "output_names": list(self.output_names) if self.output_names else None,
            **({"host_exec_ns": self.host_exec_ns} if self.host_exec_ns is not None else {}),
            **({"resident_bytes": self.resident_bytes} if self.resident_bytes is not None else {}),
            **({"locked_bytes": self.locked_bytes} if self.locked_bytes is not None else {}),
            **({"input_limits": self.input_limits} if self.input_limits is not None else {}),
        }


def nonfinite_notes(tasks: dict[str, TaskSummary]) -> list[str]:
    """A sentence for each task that sent NaN or ±inf across a connection."""
    return [f"{name}: {task.nonfinite_values} non-finite values (NaN or ±inf) crossed or tried to cross a "
            f"connection, the first {task.nonfinite_first}" for name, task in tasks.items() if task.nonfinite_values]


REAL_TIME_POLICIES = ("fifo", "rr", "deadline")
NOT_REAL_TIME_WORDS = "but did NOT run real-time"
"""In each of :func:`not_real_time_notes`' sentences (the CLI prints those on stderr instead)."""


def not_real_time_notes(tasks: dict[str, TaskSummary], requested: dict[str, str]) -> list[str]:
    """A sentence for each task that asked for a real-time policy (``requested``: task → policy) and
    ran without one (no privileges), and why. A task that asked for ``other`` got what it asked for."""
    return [f"task {name!r} asked for {requested[name]} {NOT_REAL_TIME_WORDS} ({task.policy}): "
            f"{task.rt_reason}; its timing is that of an ordinary process (run as root, e.g. through "
            "tools/as-root, or give the user an rtprio limit: docs/service.md)"
            for name, task in tasks.items()
            if requested.get(name) in REAL_TIME_POLICIES and not task.rt and task.policy != "not started"]


def limit_notes(tasks: dict[str, TaskSummary], devices: dict[str, dict[str, Any]]) -> list[str]:
    """A sentence for each device command and each guarded input whose limits acted: the values
    recorded for the controller are not what reached the device (or the reading task)."""
    notes = []
    for name, device in devices.items():
        clamped, limited = device.get("clamped_cycles") or {}, device.get("rate_limited_cycles") or {}
        for command in dict.fromkeys([*clamped, *limited]):
            acted = _acted(clamped.get(command, 0), limited.get(command, 0))
            notes.append(f"device {name!r}: command {command} {acted} (signals.csv column {name}.{command} holds "
                         "what it was sent)")
    for task in tasks.values():
        for label, counts in (task.input_limits or {}).items():
            notes.append(f"connection into {label}: "
                         f"{_acted(counts['clamped_cycles'], counts['rate_limited_cycles'])} (its guard)")
    return notes


def _acted(clamped: int, limited: int) -> str:
    said = []
    if clamped:
        said.append(f"clamped to its min/max in {clamped} {'cycle' if clamped == 1 else 'cycles'}")
    if limited:
        said.append(f"held back by its rate_per_s in {limited} {'cycle' if limited == 1 else 'cycles'}")
    return " and ".join(said)


def stale_device_notes(devices: dict[str, dict[str, Any]]) -> list[str]:
    """A sentence for each device that read stale values (summary.json ``devices``)."""
    notes = []
    for name, device in devices.items():
        if device.get("stale_reads"):
            first = (device.get("first_stale_cycles") or ["?"])[0]
            by_source = device.get("stale_reads_by_source") or {}
            sources = "; ".join(f"{source}: {count}" for source, count in by_source.items())
            lag, cycles = int(device.get("longest_lag_cycles") or 0), int(device.get("stale_cycles") or 0)
            notes.append(f"device {name!r} (task {device.get('task')}): "
                         f"{counted(int(device['stale_reads']), 'stale device read')} "
                         f"({sources or 'the last good values kept'}) in {counted(cycles, 'cycle')}, "
                         f"the first at cycle {first}, the longest lag {counted(lag, 'cycle')} "
                         "in a row. Those cycles used the last values that came: a simulation with the twin "
                         "differs from the first")
    return notes


class SignalNames(TypedDict):
    """The two TaskSummary fields :func:`signal_names` gives."""

    input_names: tuple[str, ...] | None
    output_names: tuple[str, ...] | None


def signal_names(runnable: object) -> SignalNames:
    """``input_names``/``output_names`` of a runnable, as TaskSummary fields (None if absent)."""
    def named(key: str) -> tuple[str, ...] | None:
        names = getattr(runnable, key, None)
        return tuple(str(n) for n in names) if names else None

    return SignalNames(input_names=named("input_names"), output_names=named("output_names"))


@dataclass(frozen=True, slots=True)
class PortSummary:
    """Traffic through one port."""

    direction: str
    """``in`` (non-RT → task) or ``out`` (task → non-RT)."""
    signal: str
    """The task signal it is attached to."""
    sent: int
    """Values offered: writes by clients (in) or ticks pushed by the task (out)."""
    received: int
    """Values taken: new values read by the task (in) or rows read by a client (out)."""
    dropped: int
    """Values lost: overwritten before the task read them (in) or rejected by a full queue (out)."""
    feed: dict[str, Any] | None = None
    """A port fed from a profile: ``file``, ``rows``, ``rows_delivered`` (rows whose time came
    within the run) and ``nudge`` (how live writes combine with it, or None: refused).
    ``sent``/``received``/``dropped`` then count the live writes only."""

    def to_json(self) -> dict[str, Any]:
        return {"direction": self.direction, "signal": self.signal, "sent": self.sent,
                "received": self.received, "dropped": self.dropped,
                **({"feed": self.feed} if self.feed is not None else {})}

    def describe(self) -> str:
        """What went through the port, in words (the console's line)."""
        if self.feed is None:
            return f"sent {self.sent}, received {self.received}, dropped {self.dropped}"
        feed = self.feed
        text = (f"fed from {Path(feed['file']).name}: {feed['rows_delivered']} of {feed['rows']} rows delivered, "
                "each held until the next")
        if feed.get("nudge"):
            text += (f"; live nudges ({feed['nudge']}): sent {self.sent}, received {self.received}, "
                     f"dropped {self.dropped}")
        return text


def slow_step_notes(tasks: dict[str, TaskSummary]) -> list[str]:
    """One plain sentence per task whose typical step is longer than its period."""
    notes = []
    for name, task in tasks.items():
        if task.host_exec_ns is not None:  # a simulation: what step cost on this host
            typical_ns, how = task.host_exec_ns.get("mean", 0.0), "on this host (mean, simulated)"
            consequence = "; in real time it would overrun"
        else:
            typical_ns, how = task.timing.exec_ns.p50, "(p50)"
            consequence = ""
        if typical_ns == typical_ns and typical_ns > task.period_ns:  # NaN (no cycles) says nothing
            notes.append(f"{name}'s step takes about {_about(typical_ns)} {how}; its period is "
                         f"{_exactly(task.period_ns)}{consequence}")
    return notes


def _about(ns: float) -> str:
    return f"{ns / 1e6:.1f} ms" if ns >= 1e6 else f"{ns / 1e3:.0f} µs"


def _exactly(ns: int) -> str:
    return f"{ns / 1e6:g} ms" if ns >= 1_000_000 else f"{ns / 1e3:g} µs"


@dataclass(frozen=True, slots=True)
class RunSummary:
    """Everything ``summary.json`` says about a run."""

    app: str
    """App name."""
    mode: str
    """``run`` (real time) or ``simulate`` (lock-step, offline)."""
    started: str
    """ISO 8601 wall-clock time of T0."""
    duration_s: float | None
    """Requested duration (None: until stopped)."""
    rt_capable: bool
    """Whether the supervisor's probe found real-time scheduling allowed."""
    tasks: dict[str, TaskSummary]
    """Per-task results."""
    ports: dict[str, PortSummary] = field(default_factory=dict)
    """Per-port traffic."""
    stopped_by: str = "duration"
    """``duration``, ``signal`` (Ctrl-C/SIGTERM), ``fault`` (a task failed) or ``watchdog``
    (a task stopped making progress); ``running`` while the run goes on."""
    failure: dict[str, Any] | None = None
    """The task failure that stopped the run, if any (task, cycle, phase, reason, traceback)."""
    machine: dict[str, Any] = field(default_factory=dict)
    """Kernel, preemption model, CPUs: what the numbers were measured on."""
    notes: list[str] = field(default_factory=list)
    """Anything the reader should know that has no field of its own."""
    bridges: dict[str, Any] = field(default_factory=dict)
    """ROS 2 bridge processes: state, messages passed, messages rejected (and why)."""
    hot_path: str = ""
    """Where the per-cycle framework work ran: ``c`` (compiled) or ``python`` (the fallback)."""
    elapsed_s: float = 0.0
    """Run time from T0 to the newest cycle recorded."""
    running: bool = False
    """True in the summaries rewritten while the run goes on; False in the final one."""
    devices: dict[str, Any] = field(default_factory=dict)
    """Per device (``rtloop run``): its task, kind and stale reads — how many, in how many cycles, the
    first of those cycles, the longest lag in cycles in a row, per source (a CAN frame)."""
    recording: dict[str, Any] = field(default_factory=dict)
    """The recording: ``keep_s`` (None: everything), ``stopped`` (why it stopped early, or None),
    and with ``keep_s`` the flight recorder's segment length, events and events not kept."""
    switches: list[dict[str, Any]] = field(default_factory=list)
    """Controller switches of tasks with several controllers: task, cycle (the first release the new
    controller acted on), t_s, from, to, transfer (``take_over``, an offset decay, or ``direct``)."""
    misses: dict[str, Any] = field(default_factory=dict)
    """Every deadline miss's kind and cause (a run only; ``stats/miss_causes.py:MissLedger.to_json``):
    the first ones in full with their evidence, then counts per task, kind and cause."""

    def to_json(self) -> dict[str, Any]:
        return {
            "app": self.app,
            "mode": self.mode,
            "started": self.started,
            "duration_s": self.duration_s,
            "elapsed_s": round(self.elapsed_s, 3),
            "running": self.running,
            "rt_capable": self.rt_capable,
            "stopped_by": self.stopped_by,
            "failure": self.failure,
            "machine": self.machine,
            "notes": self.notes,
            "tasks": {name: {**task.to_json(), "stale_device_reads": self.stale_device_reads(name)}
                      for name, task in self.tasks.items()},
            "ports": {name: port.to_json() for name, port in self.ports.items()},
            "bridges": self.bridges,
            "hot_path": self.hot_path,
            "devices": self.devices,
            "recording": self.recording,
            "switches": self.switches,
            **({"misses": self.misses} if self.mode == "run" else {}),
        }

    def stale_device_reads(self, task: str) -> int:
        """Stale device reads of ``task``: reads of its devices that kept the last values (a frame came
        late), summed over them (each device's count: ``devices``)."""
        return sum(int(device.get("stale_reads") or 0) for device in self.devices.values()
                   if isinstance(device, dict) and device.get("task") == task)

    def write(self, path: Path) -> None:
        path.write_text(json.dumps(self.to_json(), indent=2) + "\n")


SUMMARY_BOUND_BYTES = 64 * 1024
"""What a summary stays within (the miss causes kept in full are bounded for it: ``stats/miss_causes.py``)."""
SUMMARY_RESERVE_BYTES = 2 * SUMMARY_BOUND_BYTES
"""Disk space held for the summary from the start: two summaries' worth, since the previous one and its
replacement both exist until the rename (with one summary's worth, a run whose summary had grown past
half of it, e.g. with 20 misses kept in full, kept its last running summary on a full disk)."""


class SummaryFile:
    """``summary.json`` rewritten during a run: whole or not at all, even on a full disk.

    Each write goes to a temporary file that then replaces the summary (a rename is atomic),
    so a reader, a crash or a kill -9 sees the previous summary or the new one, never half
    of one. A reserve file holds disk space from the start; when the disk is full it is given
    up so the summary can still be written. A removed folder is made again.

    A reserve that cannot be made raises the OSError (the run must not start: its summary
    could not be promised), leaving no file behind.

    Synced to the disk (fsync before the rename): the first summary and the final one, and
    every one on a filesystem that may commit a rename before the renamed file's data. The
    summaries rewritten in between are not (``durable=False``): each fsync forces a journal
    commit and a disk cache flush, whose completion interrupts land on whatever CPU the disk's
    interrupt is bound to, a task's too. A crash of any rtloop process loses nothing by it (the
    page cache outlives a process); a power cut loses at most the rewrites of the last journal
    commit interval (ext4 writes a file renamed over another before the rename's commit:
    :func:`rename_orders_data`).
    """

    def __init__(self, out: Path) -> None:
        self.path = out / "summary.json"
        self.reserve = out / ".summary-reserve"
        self.problem = ""
        """Why the last write failed ('' if it worked)."""
        self.syncs_every_write = not rename_orders_data(out)
        """Whether every summary is synced, the ones of a running run too (see the class)."""
        self._written = False
        try:
            fd = open_new(self.reserve, 0o600)
            try:
                os.posix_fallocate(fd, 0, SUMMARY_RESERVE_BYTES)
            finally:
                os.close(fd)
        except OSError:
            with contextlib.suppress(OSError):
                self.reserve.unlink(missing_ok=True)
            raise

    def write(self, summary: RunSummary, *, durable: bool = True) -> bool:
        """Replace summary.json; returns whether it worked (failures are kept in ``problem``).

        ``durable=False``: a summary of a run still going, not synced unless this is the first one
        or the filesystem needs it (the class says why)."""
        text = json.dumps(summary.to_json(), indent=2) + "\n"
        sync = durable or self.syncs_every_write or not self._written
        for attempt in range(3):
            try:
                self._replace(text, sync=sync)
                self.problem = ""
                self._written = True
                return True
            except OSError as error:
                self.problem = f"summary.json not written: {error.strerror or error}"
                if attempt == 0 and error.errno in (errno.ENOSPC, errno.EDQUOT):
                    self.reserve.unlink(missing_ok=True)
                elif attempt == 0 and error.errno == errno.ENOENT:
                    with contextlib.suppress(OSError):
                        self.path.parent.mkdir(parents=True, exist_ok=True)
                elif error.errno in (errno.ENOSPC, errno.EDQUOT) and self._overwrite_in_place(text):
                    self.problem = ""
                    return True
        return False

    def _overwrite_in_place(self, text: str) -> bool:
        """Last resort on a full disk: write over the previous summary's own blocks.

        Only when the new text fits in them (padded with blanks, which JSON allows after the
        value), and never truncating first, so the disk needs no new block and a failure cannot
        leave an empty file where the previous summary was.
        """
        data = text.encode()
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_NOFOLLOW)
        except OSError:
            return False
        try:
            size = os.fstat(fd).st_size
            if len(data) > size:
                return False
            os.pwrite(fd, data + b" " * (size - len(data)), 0)
            os.fsync(fd)
            return True
        except OSError:
            return False
        finally:
            os.close(fd)

    def _replace(self, text: str, *, sync: bool) -> None:
        temporary = self.path.with_name(".summary.json.tmp")
        try:
            write_new(temporary, text.encode(), sync=sync)
            os.replace(temporary, self.path)
        except OSError:
            with contextlib.suppress(OSError):
                temporary.unlink()
            raise

    def close(self) -> None:
        """Give the reserved space back."""
        with contextlib.suppress(OSError):
            self.reserve.unlink()


DATA_BEFORE_RENAME_FILESYSTEMS = ("ext4", "ext3", "tmpfs", "ramfs")
"""Filesystems on which a file renamed over another is never found empty after a power cut without an
fsync: ext4 (and ext3, ext4's driver now) writes the new file's data before it commits the rename
(``auto_da_alloc``, on by default, in ``data=ordered`` mode, the default); tmpfs and ramfs lose
everything anyway."""


def rename_orders_data(folder: Path, mountinfo: str | None = None) -> bool:
    """Whether the filesystem holding ``folder`` keeps a file renamed over another whole across a power
    cut without an fsync (see :data:`DATA_BEFORE_RENAME_FILESYSTEMS`); False when it cannot be told."""
    if mountinfo is None:
        try:
            mountinfo = Path("/proc/self/mountinfo").read_text()
        except OSError:
            return False
    where = str(folder.resolve())
    best, orders = -1, False
    for line in mountinfo.splitlines():
        before, _, after = line.partition(" - ")
        fields, rest = before.split(), after.split()
        if len(fields) < 5 or len(rest) < 3:
            continue
        mount_point = fields[4].replace("\\040", " ")
        inside = where == mount_point or where.startswith(mount_point.rstrip("/") + "/")
        if inside and len(mount_point) >= best:  # the last of equally long ones is the one on top
            options = set(rest[2].split(","))
            best = len(mount_point)
            orders = (rest[0] in DATA_BEFORE_RENAME_FILESYSTEMS and "noauto_da_alloc" not in options
                      and "data=writeback" not in options)
    return orders
