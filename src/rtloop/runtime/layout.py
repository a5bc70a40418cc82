"""Shared memory of one app run: created by the supervisor, described to each task.

``AppLayout.create`` makes every segment the run needs (control block, a status block
and timing ring per task, an output channel per connected task, port and record
queues), and the :class:`~rtloop.ipc.wiring.TaskWiringPlan` each task process attaches to.
``close`` removes them all; segments of a run that died are removed by the next run.
"""

from __future__ import annotations

import inspect
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.app.guards import sent_width
from rtloop.app.plots import element_units, elements
from rtloop.app.profiles import load_profile
from rtloop.app.specs import PortSpec
from rtloop.errors import AppError, DeviceError
from rtloop.io.host import DeviceWiring
from rtloop.io.twin import TwinDevice
from rtloop.ipc.channels import LatestValue, LetChannel
from rtloop.ipc.ports import live_runs_named
from rtloop.ipc.ring import Int64Ring, SampleQueue
from rtloop.ipc.schema import (
    CONTROL_WORDS,
    STATUS_WORDS,
    TASK_TIMING_OFFSET_BYTES,
    TIMING_RECORD_WORDS,
    task_segment_size,
)
from rtloop.ipc.segments import (
    SHM_DIR,
    Segment,
    close_segments,
    new_run_token,
    open_in_shm,
    process_start_ticks,
    remove_stale_segments,
    unlink_in_shm,
)
from rtloop.ipc.status import WordBlock
from rtloop.ipc.wiring import (
    READ_LOG_WIDTH,
    InputLink,
    InputPortLink,
    OutputPortLink,
    Profile,
    TaskSegments,
    TaskWiringPlan,
    finite_checks_of,
)
from rtloop.linux import memory
from rtloop.switching import Controllers

TIMING_RING_CAPACITY = 1 << 16
RECORD_QUEUE_CAPACITY = 1 << 15
INPUT_LOG_CAPACITY = 1 << 12
READ_LOG_CAPACITY = 1 << 13
"""Stale reads a task can log between two drains (50 ms): a read per writer per cycle at 10 kHz."""
LET_SLOTS = 8


SHM_SHARE_OF_FREE = 0.5
"""An app may take at most this share of the free space of /dev/shm (other apps live there too)."""


def shared_memory_bytes(app: App) -> int:
    """Bytes of shared memory :meth:`AppLayout.create` will make for ``app`` (before creating any)."""
    total = CONTROL_WORDS * 8
    writers = {connection.source.task for connection in app.connections}
    total += sum(LetChannel.size_bytes(app.tasks[w].runnable.n_outputs, LET_SLOTS) for w in writers)
    for port in app.ports.values():
        if port.direction == "out":
            total += SampleQueue.size_bytes(port.signal.size, port.capacity)
        else:
            total += LatestValue.size_bytes(port.signal.size)
    total += len(app.tasks) * task_segment_size(TIMING_RING_CAPACITY)
    readers = {connection.target.task for connection in app.connections}
    total += len(readers) * Int64Ring.size_bytes(READ_LOG_CAPACITY, READ_LOG_WIDTH)
    for name in {ref.task for ref in app.recorded}:
        runnable = app.tasks[name].runnable
        total += SampleQueue.size_bytes(runnable.n_outputs + runnable.n_inputs, RECORD_QUEUE_CAPACITY)
    return total


def refuse_if_running(name: str, this_pid: int | None = None) -> None:
    """Refuse to start app ``name`` while a live run of the same user holds that name (with
    ``this_pid``: unless this run registered first). Two apps of one name would leave
    ``rtloop port write NAME`` to pick one in silence."""
    runs = live_runs_named(name, os.geteuid())
    if runs and runs[0].pid != this_pid:
        raise AppError(f"app {name!r} is already running (pid {runs[0].pid}); stop it first, or give this "
                       "run another name (rtloop port and top find an app by its name)")


def check_memory(app: App, shm_dir: Path = SHM_DIR, memlock_limit_bytes: int | None = None) -> int:
    """Refuse an app whose shared memory would not fit: /dev/shm free space, RLIMIT_MEMLOCK.

    ``memlock_limit_bytes``: the limit that applies (default: this process's, unless it may
    lock any amount). Returns the bytes the app needs.
    """
    from rtloop.errors import AppError
    from rtloop.linux import rt

    needed = shared_memory_bytes(app)
    stats = os.statvfs(shm_dir)
    free = stats.f_bavail * stats.f_frsize
    if needed > free * SHM_SHARE_OF_FREE:
        raise AppError(f"app {app.name!r} needs {_mb(needed)} of shared memory; {shm_dir} has {_mb(free)} free "
                       f"and an app may take at most {SHM_SHARE_OF_FREE:.0%} of it (lower port capacities or "
                       "vector sizes, or record fewer tasks)")
    if memlock_limit_bytes is None:
        capabilities = rt.probe()
        memlock_limit_bytes = capabilities.memlock_limit_bytes if capabilities.may_use_rt else None
    if memlock_limit_bytes is not None and needed > memlock_limit_bytes:
        raise AppError(f"app {app.name!r} needs {_mb(needed)} of shared memory, above RLIMIT_MEMLOCK "
                       f"({_mb(memlock_limit_bytes)}): its tasks could not lock it in memory "
                       "(raise it: ulimit -l / LimitMEMLOCK=, or lower port capacities)")
    return needed


TASK_MEMORY_SHARE_OF_AVAILABLE = 0.5
"""The task processes of a run may take at most this share of the machine's available memory:
they lock it (mlockall), and locked memory is never given back to other users' apps."""


def check_task_memory(app: App, per_task_bytes: int | None = None, available: int | None = None) -> None:
    """Refuse a run whose task processes would not fit in memory: tasks × the resident size of
    one (this process's: a task process imports what the supervisor imported, the app's modules
    included) against :data:`TASK_MEMORY_SHARE_OF_AVAILABLE` of ``MemAvailable``. Nothing is
    refused where /proc cannot say."""
    per_task_bytes = memory.resident_bytes() if per_task_bytes is None else per_task_bytes
    available = memory.available_bytes() if available is None else available
    if not per_task_bytes or available is None:
        return
    needed = len(app.tasks) * per_task_bytes
    if needed > available * TASK_MEMORY_SHARE_OF_AVAILABLE:
        raise AppError(f"app {app.name!r}: {len(app.tasks)} task processes of about {_mb(per_task_bytes)} each "
                       f"would lock {_mb(needed)}; the machine has {_mb(available)} available and a run may lock at "
                       f"most {TASK_MEMORY_SHARE_OF_AVAILABLE:.0%} of it (fewer tasks: let one task step several "
                       "runnables)")


def _mb(size_bytes: int) -> str:
    return f"{size_bytes / 1e6:.1f} MB"


def device_wiring(app: App, task: str, *, twins: bool = False) -> tuple[DeviceWiring, ...]:
    """The devices ``task`` owns, with their connections to it, as its process runs them (``twins``:
    each twin in its device's place, as ``simulate`` and ``replay`` run them)."""
    wirings = []
    for spec in app.devices.values():
        if spec.task != task:
            continue
        device = spec.device
        if twins:
            if spec.twin is None:
                raise DeviceError(spec.name, app.source, "twin", "missing: a simulation runs every device's "
                                  'twin in its place (twin = "module:Class", a Runnable)')
            device = TwinDevice(spec.name, spec.twin, spec.device, [limit.safe for limit in spec.limits])
        links = [c for c in app.device_links if spec.name in (c.source.task, c.target.task)]
        commands = tuple((c.source.slice, c.target.slice) for c in links if c.target.task == spec.name)
        out_of_it = [c for c in links if c.source.task == spec.name]
        readings = tuple((c.source.slice, c.target.slice) for c in out_of_it)
        wirings.append(DeviceWiring(device, spec.io, spec.limits, commands, readings, app.source,
                                    tuple(c.allow_nonfinite for c in out_of_it)))
    return tuple(wirings)


@dataclass
class TaskHandles:
    """The supervisor's side of one task's shared memory."""

    segments: TaskSegments
    status: WordBlock
    timing: Int64Ring
    plan: TaskWiringPlan
    record: SampleQueue | None = None
    input_log: SampleQueue | None = None
    """Port values the task took, with the release that took them (``inputs.csv``)."""
    read_log: Int64Ring | None = None
    """Reads of connections that got another sample than logical execution time promised (``reads.csv``)."""


@dataclass
class AppLayout:
    app: App
    token: str
    control: WordBlock
    tasks: dict[str, TaskHandles]
    input_ports: dict[str, LatestValue]
    output_ports: dict[str, SampleQueue]
    segments: list[Segment] = field(default_factory=list)
    registry_path: Path | None = None

    mode: str = "run"
    """``run`` (real time: the run holds its app's name while it lives) or ``simulate``."""

    @classmethod
    def create(cls, app: App, summary_path: Path | None = None, mode: str = "run") -> AppLayout:
        """Every segment of a run; ``summary_path`` (the live summary.json) goes into the registry."""
        check_memory(app)
        remove_stale_segments()
        if mode == "run":
            check_task_memory(app)
            refuse_if_running(app.name)  # early, before anything is created; _write_registry decides
        token = new_run_token()
        owner = os.getpid()
        segments: list[Segment] = []

        def segment(what: str, size_bytes: int) -> Segment:
            created = Segment.create(app.name, owner, token, what, size_bytes)
            segments.append(created)
            return created

        try:
            return cls._build(app, token, segment, segments, summary_path, mode)
        except BaseException:
            for created in segments:
                created.unlink()
            close_segments(segments)
            raise

    @classmethod
    def _build(cls, app: App, token: str, segment: Callable[[str, int], Segment], segments: list[Segment],
               summary_path: Path | None, mode: str) -> AppLayout:
        control_segment = segment("control", CONTROL_WORDS * 8)
        control = WordBlock(control_segment, 0, CONTROL_WORDS)

        channels: dict[str, str] = {}
        for connection in app.connections:
            writer = connection.source.task
            if writer not in channels:
                n_values = app.tasks[writer].runnable.n_outputs
                created = segment(f"{writer}.y", LetChannel.size_bytes(n_values, LET_SLOTS))
                LetChannel.initialise(created, n_values, LET_SLOTS)
                channels[writer] = created.name

        input_ports: dict[str, LatestValue] = {}
        output_ports: dict[str, SampleQueue] = {}
        port_links: dict[str, list[InputPortLink | OutputPortLink]] = {name: [] for name in app.tasks}
        for port in app.ports.values():
            created, link = cls._port(app, port, segment)
            if isinstance(link, InputPortLink):
                input_ports[port.name] = LatestValue(created)
            else:
                output_ports[port.name] = SampleQueue(created)
            port_links[port.signal.task].append(link)

        recorded_tasks = {ref.task for ref in app.recorded}
        tasks: dict[str, TaskHandles] = {}
        for name, spec in app.tasks.items():
            task_segment = segment(f"{name}.task", task_segment_size(TIMING_RING_CAPACITY))
            status = WordBlock(task_segment, 0, STATUS_WORDS)
            timing = Int64Ring.initialise(task_segment, TIMING_RING_CAPACITY, TIMING_RECORD_WORDS,
                                           TASK_TIMING_OFFSET_BYTES)
            record = None
            if name in recorded_tasks:  # [y…, u…, what its devices were sent…]
                width = spec.runnable.n_outputs + spec.runnable.n_inputs + sent_width(app, name)
                record_segment = segment(f"{name}.record", SampleQueue.size_bytes(width, RECORD_QUEUE_CAPACITY))
                record = SampleQueue.initialise(record_segment, width, RECORD_QUEUE_CAPACITY)
            inputs = tuple(
                InputLink(
                    channels[c.source.task], c.source.slice, c.target.slice,
                    app.tasks[c.source.task].config.period_ns, c.source.task,
                    c.min, c.max, c.rate_per_s * spec.config.period_ns * 1e-9,
                )
                for c in app.connections
                if c.target.task == name
            )
            links = port_links[name]
            wanted = {channels.get(name)} | {link.channel_segment for link in inputs}
            wanted |= {link.segment for link in links}
            if record is not None:
                wanted.add(record_segment.name)
            # every port that takes live writes logs them (a profile's live nudges too), for replay
            live = [link for link in links if isinstance(link, InputPortLink)
                    and (link.profile is None or link.nudge is not None)]
            input_log = input_log_segment = None
            if live:
                width = 1 + max(link.target.stop - link.target.start for link in live)
                input_log_segment = segment(f"{name}.inputs", SampleQueue.size_bytes(width, INPUT_LOG_CAPACITY))
                input_log = SampleQueue.initialise(input_log_segment, width, INPUT_LOG_CAPACITY)
                wanted.add(input_log_segment.name)
            read_log = read_log_segment = None
            if inputs:
                read_log_segment = segment(f"{name}.reads", Int64Ring.size_bytes(READ_LOG_CAPACITY, READ_LOG_WIDTH))
                read_log = Int64Ring.initialise(read_log_segment, READ_LOG_CAPACITY, READ_LOG_WIDTH)
                wanted.add(read_log_segment.name)
            plan = TaskWiringPlan(
                output_channel=channels.get(name),
                inputs=inputs,
                input_ports=tuple(link for link in links if isinstance(link, InputPortLink)),
                output_ports=tuple(link for link in links if isinstance(link, OutputPortLink)),
                record_queue=record_segment.name if record is not None else None,
                input_log=input_log_segment.name if input_log_segment is not None else None,
                read_log=read_log_segment.name if read_log_segment is not None else None,
                segments=tuple(sorted(w for w in wanted if w)),
                sent_width=sent_width(app, name),
                finite_checks=finite_checks_of(
                    name, [(c.source.slice, c.allow_nonfinite) for c in app.connections if c.source.task == name],
                    getattr(spec.runnable, "output_names", None)),
            )
            segments_of_task = TaskSegments(control_segment.name, task_segment.name)
            tasks[name] = TaskHandles(segments_of_task, status, timing, plan, record, input_log, read_log)
        layout = cls(app, token, control, tasks, input_ports, output_ports, segments, mode=mode)
        layout._write_registry(summary_path)
        return layout

    @staticmethod
    def _port(app: App, port: PortSpec,
              segment: Callable[[str, int], Segment]) -> tuple[Segment, InputPortLink | OutputPortLink]:
        ref = port.signal
        if port.direction == "out":
            created = segment(f"port.{port.name}", SampleQueue.size_bytes(ref.size, port.capacity))
            SampleQueue.initialise(created, ref.size, port.capacity)
            return created, OutputPortLink(port.name, created.name, ref.slice)
        profile = None
        if port.feed is not None:
            t_ns, values = load_profile(port.feed, ref.size, f"port {port.name!r}", port.value_range)
            profile = Profile(t_ns, values)
        starts = getattr(app.tasks[ref.task].runnable, "input_start_values", None)
        default = list(starts[ref.slice]) if starts is not None else [0.0] * ref.size  # a tunable keeps its start
        initial = np.array(port.initial if port.initial is not None else default, dtype=np.float64)
        nudge = port.nudge if profile is not None else None
        if nudge == "offset":
            initial = np.zeros(ref.size)  # no offset until one is written
        created = segment(f"port.{port.name}", LatestValue.size_bytes(ref.size))
        LatestValue.initialise(created, initial, fed_by_profile=profile is not None and nudge is None)
        return created, InputPortLink(port.name, created.name, ref.slice, profile, nudge)

    # --- registry: how `rtloop port` and bridges find a running app's ports -------------
    def _write_registry(self, summary_path: Path | None) -> None:
        units = element_units(self.app)
        ports = {
            name: {
                "direction": spec.direction,
                "segment": self._port_segment(name),
                "signal": str(spec.signal),
                "size": spec.signal.size,
                "allow_nonfinite": spec.allow_nonfinite,
                "range": list(spec.value_range) if spec.value_range is not None else None,
                "names": _element_names(self.app, spec),
                "units": [units.get(element, "") for element in elements(spec.signal)],
                "period_ns": self.app.tasks[spec.signal.task].config.period_ns,
                **_switch_facts(self.app, spec),
            }
            for name, spec in self.app.ports.items()
        }
        registry = {
            "app": self.app.name,
            "pid": os.getpid(),
            "pid_start_ticks": process_start_ticks(os.getpid()),
            "mode": self.mode,
            "ports": ports,
            "tasks": {name: handles.segments.task for name, handles in self.tasks.items()},
            "control": next(iter(self.tasks.values())).segments.control if self.tasks else None,
            "summary": str(summary_path.resolve()) if summary_path is not None else None,
        }
        path = SHM_DIR / f"rtloop-{self.app.name}-{os.getpid()}-{self.token}-registry.json"
        fd = open_in_shm(path.name, os.O_CREAT | os.O_WRONLY | os.O_EXCL)
        with os.fdopen(fd, "w") as file:
            json.dump(registry, file, indent=1)
        if self.mode == "run":
            try:  # two runs started at once both see each other now: the first registered keeps the name
                refuse_if_running(self.app.name, this_pid=os.getpid())
            except AppError:
                unlink_in_shm(path.name)
                raise
        self.registry_path = path

    def _port_segment(self, port: str) -> str:
        suffix = f"-port.{port}"
        return next(s.name for s in self.segments if s.name.endswith(suffix))

    def close(self) -> None:
        """Remove every segment of this run and let go of it here: the layout's views are dropped,
        then each segment's descriptors and mapping are closed (the caller's process goes on)."""
        for created in self.segments:
            created.unlink()
        if self.registry_path is not None:
            unlink_in_shm(self.registry_path.name)
        self.tasks, self.input_ports, self.output_ports = {}, {}, {}
        del self.control
        close_segments(self.segments)


def _switch_facts(app: App, spec: PortSpec) -> dict[str, Any]:
    """What `rtloop switch` needs of a task's switch port: its controllers' names, in index order."""
    runnable = app.tasks[spec.signal.task].runnable
    if not isinstance(runnable, Controllers) or spec.direction != "in" or spec.signal.slice != runnable.switch_slice:
        return {}
    sources = {name: _source_file(controller) for name, controller in zip(runnable.names, runnable.alternatives,
                                                                           strict=True)}
    return {"controllers": list(runnable.names), "switch_task": spec.signal.task, "sources": sources}


def _source_file(runnable: object) -> str | None:
    """The file a controller's class comes from (what `rtloop reload` reads again), if it has one."""
    try:
        found = inspect.getsourcefile(type(runnable))
    except TypeError:  # a class of a compiled module
        return None
    return str(Path(found).resolve()) if found else None


def _element_names(app: App, spec: PortSpec) -> list[str]:
    """The name the runnable gives each value of a port ('' where it gives none): ``rtloop port list``."""
    ref = spec.signal
    runnable = app.tasks[ref.task].runnable
    names = list(getattr(runnable, "input_names" if ref.side == "u" else "output_names", None) or ())
    return [str(names[i]) if i < len(names) else "" for i in range(ref.start, ref.stop)]
