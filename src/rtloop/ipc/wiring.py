"""A task's view of the app's wiring: what it reads before ``step`` and publishes after.

The supervisor decides the wiring and hands each task a :class:`TaskWiringPlan`
(names of shared-memory segments and slices, picklable). Inside the task process,
:meth:`TaskWiring.attach` maps them once; ``read_inputs`` and ``publish_outputs`` then
run every cycle without allocating.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np

from rtloop.errors import NonFiniteOutput
from rtloop.ipc.channels import NO_STAMP, LatestValue, LetChannel
from rtloop.ipc.ring import Int64Ring, SampleQueue
from rtloop.ipc.schema import INITIAL_STAMP, READ_LOG_RECORD_WORDS, NudgeMode, PortWord, SlotWord
from rtloop.ipc.segments import Segment, close_segments
from rtloop.ipc.status import StatusWord, WordBlock


@dataclass(frozen=True, slots=True)
class TaskSegments:
    """Names of the shared memory a task process attaches to (layout: ``schema``)."""

    control: str
    """The app's control block (T0, end time, stop flag)."""
    task: str
    """This task's status block followed by its timing ring."""


@dataclass(frozen=True, slots=True)
class InputLink:
    """A connection into this task: another task's ``y[source]`` → this task's ``u[target]``."""

    channel_segment: str
    source: slice
    target: slice
    writer_period_ns: int
    writer: str = ""
    """The writing task's name (names the link in the read log, ``reads.csv``)."""
    low: float = -math.inf
    """The connection's guard (``app/guards.py``): values read are clamped to ``[low, high]``..."""
    high: float = math.inf
    step_max: float = math.inf
    """...and move by at most this much per cycle of the reader (``rate_per_s · P``)."""

    @property
    def guarded(self) -> bool:
        return self.low > -math.inf or self.high < math.inf or self.step_max < math.inf


READ_LOG_WIDTH = READ_LOG_RECORD_WORDS
"""A read-log record, times in ns since T0: ``[release, writer index, stamp got (or NO_STAMP), stamp due]``."""


@dataclass(frozen=True, slots=True)
class Profile:
    """A setpoint profile, piecewise constant, evaluated at each release time."""

    t_ns: np.ndarray
    """Times since T0 at which a row starts to hold (int64, increasing)."""
    values: np.ndarray
    """One row per time (float64)."""


NUDGE_MODES = {"offset": NudgeMode.OFFSET, "override": NudgeMode.OVERRIDE}
"""How live writes combine with a port's profile (0: no live writes to a fed port)."""


@dataclass(frozen=True, slots=True)
class InputPortLink:
    """A port feeding this task's ``u[target]``: live values, or a profile (plus live nudges)."""

    name: str
    segment: str
    target: slice
    profile: Profile | None = None
    nudge: str | None = None
    """With a profile: ``offset`` (u = profile + the latest live value) or ``override`` (the
    newest of a profile row and a live write holds), else None (live writes refused)."""


@dataclass(frozen=True, slots=True)
class OutputPortLink:
    """A port receiving this task's ``y[source]`` every tick."""

    name: str
    segment: str
    source: slice


@dataclass(frozen=True, slots=True)
class FiniteCheck:
    """An output that crosses a connection: a NaN or ±inf there is counted, and a fault unless allowed."""

    index: int
    """Its place in ``y``."""
    fault: bool
    """False only when every connection from it says ``allow_nonfinite``."""
    label: str
    """How messages name it: ``plant.y[1] (speed)``."""


@dataclass(frozen=True, slots=True)
class TaskWiringPlan:
    output_channel: str | None = None
    inputs: tuple[InputLink, ...] = ()
    input_ports: tuple[InputPortLink, ...] = ()
    output_ports: tuple[OutputPortLink, ...] = ()
    record_queue: str | None = None
    """Segment of the queue carrying ``[y…, u…]`` of every tick to the recorder."""
    input_log: str | None = None
    """Segment of the queue carrying ``[port index, values…]`` each time a live input port
    delivers a new value, stamped with the release (ns since T0) that took it (for replay)."""
    read_log: str | None = None
    """Segment of the ring of reads that did not get the sample logical execution time promised
    (a stale read): one ``READ_LOG_WIDTH`` record each, nothing in a clean cycle (for replay)."""
    segments: tuple[str, ...] = field(default=())
    finite_checks: tuple[FiniteCheck, ...] = ()
    """Outputs crossing a connection, checked for NaN and ±inf before they are published."""
    sent_width: int = 0
    """Commands the task's devices are sent each cycle, recorded after ``u`` (``TaskWiring.sent``)."""

    def writers(self) -> list[str]:
        """The writing tasks in the order the task reads them (the writer index of the read log)."""
        return list(dict.fromkeys(link.writer for link in self.inputs))


class _WriterLink:
    """Every connection from one writer: one seqlock read per cycle, then a copy per connection."""

    __slots__ = ("channel", "copies", "first", "period_ns", "scratch", "sources", "spans", "writer")

    def __init__(self, channel: LetChannel, links: list[InputLink], u: np.ndarray) -> None:
        self.channel, self.period_ns, self.writer = channel, links[0].writer_period_ns, links[0].writer
        self.first = min(link.source.start for link in links)
        stop = max(link.source.stop for link in links)
        self.sources = channel.source_views(slice(self.first, stop))
        self.scratch = np.zeros(stop - self.first)  # a torn read never reaches u
        self.spans = tuple(
            (link.source.start - self.first, link.target.start, link.source.stop - link.source.start) for link in links
        )
        self.copies = [(self.scratch[a : a + n], u[b : b + n]) for a, b, n in self.spans]


class _ProfileReader:
    __slots__ = ("index", "live_port", "mode", "nudge", "port", "profile", "t_ns", "target", "values")

    def __init__(self, profile: Profile, target: np.ndarray, mode: int = 0, nudge: np.ndarray | None = None,
                 live_port: int = -1, port: str = "") -> None:
        self.profile, self.port = profile, port
        self.t_ns = [int(t) for t in profile.t_ns]
        self.values = [np.array(row, dtype=np.float64) for row in profile.values]
        self.target = target
        self.index = -1
        self.mode, self.nudge, self.live_port = mode, nudge, live_port
        """Live nudges: NUDGE_MODES value, the live value's buffer, its place among live ports."""

    def read(self, since_t0_ns: int, fresh: list[bool]) -> None:
        index = self.index
        while index + 1 < len(self.t_ns) and self.t_ns[index + 1] <= since_t0_ns:
            index += 1
        changed = index != self.index and index >= 0
        if changed:
            self.index = index
        if self.mode == 0:
            if changed:
                self.target[:] = self.values[index]
        elif self.mode == 1:  # offset: the row in force plus the latest live value, every release
            if self.index >= 0:
                np.add(self.values[self.index], self.nudge, out=self.target)  # type: ignore[arg-type]  # a nudge mode comes with its buffer
        elif fresh[self.live_port]:  # override: a live write arrived at this release
            self.target[:] = self.nudge
        elif changed:  # override: a new row starts and holds until the next write
            self.target[:] = self.values[index]


class InputGuards:
    """The guards of a task's guarded connections, applied to ``u`` right after the inputs are read.

    One flat vector per bound over every guarded element, allocated once; per cycle: clamp to
    ``[low, high]``, then a step of at most ``step_max`` from the value held before (``last``:
    the input's start value before T0), each counted per element (``clamped``, ``rate_limited``)
    — the arithmetic and order of ``io/limits.py:CommandGuard`` and of the C core's."""

    __slots__ = ("clamped", "delta", "gather", "held", "high", "hit", "indices", "last", "low", "out", "rate_limited",
                 "scatter", "spans", "step_max", "step_min", "targets", "values")

    def __init__(self, links: Sequence[InputLink], u: np.ndarray) -> None:
        guarded = [link for link in links if link.guarded]
        self.spans = tuple((link.target.start, link.target.stop - link.target.start) for link in guarded)
        """(first element of ``u``, how many) per guarded connection, for the C core."""
        self.targets = [u[link.target] for link in guarded]
        count = sum(n for _, n in self.spans)
        self.low = np.array([link.low for link in guarded for _ in range(link.target.start, link.target.stop)])
        self.high = np.array([link.high for link in guarded for _ in range(link.target.start, link.target.stop)])
        self.step_max = np.array([link.step_max for link in guarded for _ in range(link.target.start,
                                                                                    link.target.stop)])
        self.step_min = -self.step_max
        self.last = np.array([u[i] for link in guarded for i in range(link.target.start, link.target.stop)],
                             dtype=np.float64)
        self.values, self.out, self.delta = np.zeros(count), np.zeros(count), np.zeros(count)
        self.hit, self.held = np.zeros(count, dtype=bool), np.zeros(count, dtype=bool)
        starts = np.cumsum([0, *(n for _, n in self.spans)]).tolist()
        self.indices = np.array([start + i for start, n in self.spans for i in range(n)], dtype=np.int64)
        """The element of ``u`` each guarded value is (for the C core)."""
        views = [slice(starts[k], starts[k] + n) for k, (_, n) in enumerate(self.spans)]  # views made once
        self.gather = [(self.values[v], target) for v, target in zip(views, self.targets, strict=True)]
        self.scatter = [(target, self.out[v]) for v, target in zip(views, self.targets, strict=True)]
        self.clamped = np.zeros(count, dtype=np.int64)
        self.rate_limited = np.zeros(count, dtype=np.int64)

    def __bool__(self) -> bool:
        return bool(self.spans)

    def apply(self) -> None:
        """Guard the values just read, in place (the Python twin of the C core's guard): plain
        ufuncs with ``out=``, nothing allocated. A value the rate limit does not hold back is left
        as clamped (``last + (value − last)`` could differ from it in the last bit)."""
        values, out, last, delta, hit, held = self.values, self.out, self.last, self.delta, self.hit, self.held
        for into, target in self.gather:
            np.copyto(into, target)
        np.minimum(values, self.high, out=out)
        np.maximum(out, self.low, out=out)
        np.not_equal(out, values, out=hit)
        np.add(self.clamped, hit, out=self.clamped)
        np.subtract(out, last, out=delta)
        np.greater(delta, self.step_max, out=hit)
        np.less(delta, self.step_min, out=held)
        np.logical_or(hit, held, out=hit)
        np.add(self.rate_limited, hit, out=self.rate_limited)
        np.minimum(delta, self.step_max, out=delta)
        np.maximum(delta, self.step_min, out=delta)
        np.add(last, delta, out=delta)
        np.copyto(out, delta, where=hit)
        np.copyto(last, out)
        for target, guarded in self.scatter:
            np.copyto(target, guarded)

    def counts(self, task: str, names: Sequence[str] | None) -> dict[str, dict[str, int]]:
        """Per guarded input that acted: ``{"plant.u[0] (force_N)": {"clamped_cycles", "rate_limited_cycles"}}``."""
        out = {}
        for j, index in enumerate(self.indices.tolist()):
            clamped, limited = int(self.clamped[j]), int(self.rate_limited[j])
            if clamped or limited:
                name = f" ({names[index]})" if names and index < len(names) and names[index] else ""
                out[f"{task}.u[{index}]{name}"] = {"clamped_cycles": clamped, "rate_limited_cycles": limited}
        return out


class TaskWiring:
    """The wiring of one task, attached inside its process."""

    def __init__(self, plan: TaskWiringPlan, u: np.ndarray, y: np.ndarray, status: WordBlock | None) -> None:
        self._segments = {name: Segment.attach(name) for name in plan.segments}
        self.status = status
        self.stale_reads = 0
        self.t0_ns = 0
        self.u, self.y = u, y
        self.output = LetChannel(self._segments[plan.output_channel]) if plan.output_channel else None
        by_writer: dict[str, list[InputLink]] = {}
        for link in plan.inputs:
            by_writer.setdefault(link.channel_segment, []).append(link)
        self.links = [_WriterLink(LetChannel(self._segments[name]), links, u) for name, links in by_writer.items()]
        self.read_log = Int64Ring(self._segments[plan.read_log]) if plan.read_log else None
        # A live port writes its slice of u, or, for a profile's nudges, a buffer of its own.
        self.live_ports: list[tuple[LatestValue, np.ndarray, float]] = []
        self.profiles: list[_ProfileReader] = []
        for index, port in enumerate(plan.input_ports):
            target = u[port.target]
            if port.profile is None or port.nudge is not None:
                nudge = np.zeros(len(target)) if port.profile is not None else None
                self.live_ports.append((LatestValue(self._segments[port.segment]),
                                        target if nudge is None else nudge, float(index)))
            if port.profile is not None:
                mode = NUDGE_MODES.get(port.nudge or "", 0)
                nudge_port = len(self.live_ports) - 1 if mode else -1
                self.profiles.append(_ProfileReader(port.profile, target, mode,
                                                    self.live_ports[nudge_port][1] if mode else None, nudge_port,
                                                    port.name))
        self.fresh = [False] * len(self.live_ports)
        self.input_log = SampleQueue(self._segments[plan.input_log]) if plan.input_log else None
        self.input_log_row = np.zeros(self.input_log.n_values if self.input_log is not None else 0)
        self.output_ports = [
            (SampleQueue(self._segments[port.segment]), y[port.source]) for port in plan.output_ports
        ]
        self.record = SampleQueue(self._segments[plan.record_queue]) if plan.record_queue else None
        self.sent = np.zeros(plan.sent_width)
        """What the task's devices were sent last (their guards write it), recorded after ``u``."""
        self.record_row = np.zeros(len(y) + len(u) + plan.sent_width)
        self.record_y = self.record_row[: len(y)]
        self.record_u = self.record_row[len(y) : len(y) + len(u)]
        self.record_sent = self.record_row[len(y) + len(u) :]
        self.guards = InputGuards(plan.inputs, u)
        self.initial_y = y.copy()
        self.finite_checks = plan.finite_checks

    def held_nudges(self) -> tuple[tuple[str, tuple[float, ...]], ...]:
        """(port, its latest live value) of each profile port taking live nudges: part of the task's
        state a ``--keep`` snapshot keeps, for it is not in ``u`` (an offset is added to the profile's
        row at every release; an override waits for the next row)."""
        return tuple((reader.port, tuple(reader.nudge.tolist())) for reader in self.profiles
                     if reader.nudge is not None)

    def recent_outputs(self) -> tuple[tuple[int, tuple[float, ...]], ...]:
        """(stamp since T0, values) of the samples still in this task's output channel, oldest first:
        what a late reader may still get (a ``--keep`` snapshot keeps them). Called by the writer itself."""
        channel = self.output
        if channel is None:
            return ()
        samples = []
        for base, values in zip(channel.bases, channel.values, strict=True):
            stamp = channel.words[base + SlotWord.STAMP_NS]
            if stamp != NO_STAMP:
                samples.append((0 if stamp == INITIAL_STAMP else stamp - self.t0_ns, tuple(values.tolist())))
        return tuple(sorted(samples))

    def resume_profiles(self, since_t0_ns: int, nudges: dict[str, tuple[float, ...]]) -> None:
        """Profiles as they stood after the release at ``since_t0_ns`` (a replay resuming a snapshot, before
        the cycle work is built): the row in force then, and the live nudges held (``held_nudges``)."""
        for reader in self.profiles:
            index = reader.index
            while index + 1 < len(reader.t_ns) and reader.t_ns[index + 1] <= since_t0_ns:
                index += 1
            reader.index = index
            if reader.nudge is not None and reader.port in nudges:
                # the port holds the value too (each read copies it again), seen already: not fresh
                port, buffer, _index = self.live_ports[reader.live_port]
                port.write(np.asarray(nudges[reader.port], dtype=np.float64))
                port.last_seq_seen = port.words[PortWord.SEQ]
                buffer[:] = nudges[reader.port]

    def check_finite(self, cycle: int, y: np.ndarray) -> None:
        """Count NaN and ±inf headed across a connection; raise NonFiniteOutput where not allowed."""
        for check in self.finite_checks:
            value = float(y[check.index])
            if math.isfinite(value):
                continue
            status = self.status
            if status is not None:
                if not status[StatusWord.NONFINITE_VALUES]:
                    status[StatusWord.NONFINITE_FIRST_CYCLE] = cycle
                    status[StatusWord.NONFINITE_FIRST_OUTPUT] = check.index
                status[StatusWord.NONFINITE_VALUES] += 1
            if check.fault:
                raise NonFiniteOutput(f"{check.label} is {value!r} at cycle {cycle}: a non-finite value crossing "
                                      "a connection is a fault (allow_nonfinite = true on the connection lets it "
                                      "through)")

    def read_inputs(self, release_ns: int, u: np.ndarray, instead: dict[int, np.ndarray | None] | None = None) -> None:
        """Read the inputs valid at ``release_ns`` into ``u``, then guard them. ``instead`` (a replay's
        stale reads): per link index, what the run read in its place (``link.scratch``'s layout), or
        None for nothing read; the guards act on it as they did in the run."""
        t0_ns = self.t0_ns
        if instead is not None:
            self._check_instead(instead)
        for index, link in enumerate(self.links):
            if instead is not None and index in instead:
                read_then = instead[index]
                if read_then is not None:
                    for a, b, n in link.spans:
                        u[b : b + n] = read_then[a : a + n]
                continue
            stamp = link.channel.read_valid_at(release_ns, link.sources, link.scratch)
            if stamp == INITIAL_STAMP:  # the writer's initial outputs, published before T0: valid from T0
                stamp = t0_ns
            if stamp != NO_STAMP:
                for source, target in link.copies:
                    np.copyto(target, source)
            entitled = t0_ns + (release_ns - t0_ns) // link.period_ns * link.period_ns
            if stamp < entitled:  # the writer has not published what we are entitled to
                self.stale_reads += 1
                if self.status is not None:
                    self.status[StatusWord.STALE_READS] = self.stale_reads
                if self.read_log is not None:  # what the task got instead, for replay
                    got = stamp if stamp == NO_STAMP else stamp - t0_ns
                    self.read_log.push4(release_ns - t0_ns, index, got, entitled - t0_ns)
        if self.guards:
            self.guards.apply()
        fresh = self.fresh
        for position, (port, target, port_index) in enumerate(self.live_ports):
            seen = port.last_seq_seen
            port.read_into(target)
            fresh[position] = port.last_seq_seen != seen
            if fresh[position] and self.input_log is not None:
                self._log_input(self.input_log, release_ns - t0_ns, port_index, target)
        for profile in self.profiles:
            profile.read(release_ns - t0_ns, fresh)

    def _check_instead(self, instead: dict[int, np.ndarray | None]) -> None:
        """The C core's checks of a replay's ``instead``, with the same exceptions."""
        if not isinstance(instead, dict):
            raise TypeError("read_inputs' instead must be a dict")
        for index, read_then in instead.items():
            if not isinstance(index, int):
                raise TypeError(f"read_inputs' instead names input {index!r}, not an index")
            if not 0 <= index < len(self.links):
                raise ValueError(f"read_inputs' instead names input {index} of {len(self.links)}")
            width = len(self.links[index].scratch)
            if read_then is not None and np.shape(read_then) != (width,):
                raise ValueError(f"read_inputs' instead for input {index} holds {np.shape(read_then)} values, "
                                 f"not {width}")

    def _log_input(self, log: SampleQueue, since_t0_ns: int, index: float, values: np.ndarray) -> None:
        """A port delivered a new value at this release: log it so the run can be replayed."""
        row = self.input_log_row
        row[0] = index
        row[1 : 1 + len(values)] = values
        row[1 + len(values) :] = 0.0
        log.push(since_t0_ns, row)

    def publish_outputs(self, cycle: int, publish_ns: int, y: np.ndarray) -> None:
        if self.finite_checks:
            self.check_finite(cycle, y)  # before anything leaves: a NaN never crosses unless allowed
        if self.output is not None:
            self.output.publish(publish_ns, y)
        for queue, source in self.output_ports:
            queue.push(cycle, source)
        if self.record is not None:
            np.copyto(self.record_y, y)
            np.copyto(self.record_u, self.u)
            np.copyto(self.record_sent, self.sent)
            self.record.push(cycle, self.record_row)

    def publish_initial(self, y: np.ndarray) -> None:
        """Publish the outputs left by ``prerun`` (initial conditions), valid from T0.

        Called before the task is ready, so before T0 is known and before any task's first release:
        stamped :data:`INITIAL_STAMP`, which readers take as T0. A reader released at T0 finds them
        even when this task sees T0 late (a loaded machine), as in a simulation."""
        self.initial_y[:] = y
        if self.output is not None:
            self.output.publish(INITIAL_STAMP, self.initial_y)

    def stamp_initial(self, t0_ns: int, *, last_cycle: int = -1, period_ns: int = 0) -> None:
        """Take T0 and record the initial outputs as those of ``last_cycle`` (-1: before the first).

        A replay that resumes a task from a snapshot passes the cycle the snapshot followed: its
        outputs (``initial_y``) are published again, stamped as that cycle's."""
        self.t0_ns = t0_ns
        if self.output is not None and last_cycle >= 0:
            self.output.publish(t0_ns + (last_cycle + 1) * period_ns, self.initial_y)
        if self.record is not None:  # tick -1: the outputs that hold from T0 (signals.csv row t = 0)
            np.copyto(self.record_y, self.initial_y)
            np.copyto(self.record_u, self.u)
            self.record.push(last_cycle, self.record_row)

    def close(self) -> None:
        """Let go of the shared memory in a process that goes on (the simulator's): the views are
        dropped, then the segments closed (a task process just ends)."""
        self.output = self.read_log = self.input_log = self.record = None
        self.links, self.live_ports, self.output_ports = [], [], []
        segments, self._segments = list(self._segments.values()), {}
        close_segments(segments)



def finite_checks_of(task: str, connections: Iterable[tuple[slice, bool]], output_names: Sequence[str] | None
                     ) -> tuple[FiniteCheck, ...]:
    """The outputs of ``task`` that cross a connection (source slice, allow_nonfinite), once each."""
    allowed: dict[int, bool] = {}
    for source, allow in connections:
        for index in range(source.start, source.stop):
            allowed[index] = allowed.get(index, True) and allow
    checks = []
    for index in sorted(allowed):
        name = f" ({output_names[index]})" if output_names and index < len(output_names) else ""
        checks.append(FiniteCheck(index, not allowed[index], f"{task}.y[{index}]{name}"))
    return tuple(checks)


class NonfiniteFields(TypedDict):
    """The two TaskSummary fields :func:`nonfinite_fields` gives."""

    nonfinite_values: int
    nonfinite_first: str


def nonfinite_fields(status: WordBlock, plan: TaskWiringPlan) -> NonfiniteFields:
    """``nonfinite_values`` and ``nonfinite_first`` of a task's summary, from its status block."""
    count = status[StatusWord.NONFINITE_VALUES]
    if not count:
        return {"nonfinite_values": 0, "nonfinite_first": ""}
    index, cycle = status[StatusWord.NONFINITE_FIRST_OUTPUT], status[StatusWord.NONFINITE_FIRST_CYCLE]
    label = next((check.label for check in plan.finite_checks if check.index == index), f"y[{index}]")
    return {"nonfinite_values": count, "nonfinite_first": f"{label} at cycle {cycle}"}
