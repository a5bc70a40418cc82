"""The records an app is described with: tasks, signals, devices, connections, ports, ROS 2
topics and the live view, with the bounds they are checked against. :class:`~rtloop.app.builder.App`
makes them (each checked as it is added); everything that runs an app reads them.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from rtloop.errors import AppError, DeviceError
from rtloop.io.device import CommandLimit, Device
from rtloop.runnable import Runnable
from rtloop.text import clip, shorten

Side = Literal["u", "y"]
NAME_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,31}$")
"""App, task and port names: letters, digits, underscores, at most 32 characters (they become
parts of shared-memory file names)."""
OVERRUN_POLICIES = ("skip", "catch_up")
MIN_PERIOD_NS = 10_000
MAX_PERIOD_NS = 3600 * 1_000_000_000
"""Periods from 10 µs (100 kHz) to one hour."""
MAX_VECTOR_SIZE = 1 << 16
"""Inputs or outputs of one runnable: at most 65536 values."""
MAX_PORT_CAPACITY = 1 << 20
"""Samples an output port may queue."""
MAX_TASKS = 64
"""Tasks of one app: each runs in a process of its own that locks its memory (≈ 35 MB each),
and locked memory cannot be reclaimed: a generated app of hundreds would take the machine."""
MAX_DURATION_S = 1e8
"""About three years: a longer run is a controller that runs until stopped."""
DEFAULT_WATCHDOG_PERIODS = 1000
WATCHDOG_MIN_S = 10.0

@dataclass(frozen=True, slots=True)
class TaskConfig:
    """How a task runs: its timing and its place on the machine."""

    name: str
    """Unique name within the app (used in signal names, e.g. ``plant.y[0]``)."""
    period_ns: int
    """Period P; releases happen at T0 + k·P."""
    priority: int = 80
    """Real-time priority (1–99 for fifo/rr; ignored for other)."""
    cpu: int | None = None
    """CPU to pin the task to (None: any)."""
    policy: str = "fifo"
    """Scheduling policy: fifo, rr, other or deadline."""
    overrun: str = "skip"
    """After an overrun: ``skip`` the missed releases or ``catch_up`` on them."""
    watchdog_periods: int = DEFAULT_WATCHDOG_PERIODS
    """The supervisor stops the app when no cycle of this task finishes for this many periods
    (at least ``WATCHDOG_MIN_S``): the step is stuck. 0 turns the watchdog off."""
    max_consecutive_misses: int | None = None
    """Stop the app after this many deadline misses in a row (None: count them and go on)."""
    lock_blas_buffer: bool = False
    """Keep OpenBLAS's 32 MB work buffer locked in memory (for steps doing large matrix products)."""


@dataclass(frozen=True, slots=True)
class SignalRef:
    """A contiguous slice of a task's input (``u``) or output (``y``) vector."""

    task: str
    side: Side
    start: int
    stop: int

    @property
    def size(self) -> int:
        return self.stop - self.start

    @property
    def slice(self) -> slice:
        return slice(self.start, self.stop)

    def names(self) -> list[str]:
        return [f"{self.task}.{self.side}[{i}]" for i in range(self.start, self.stop)]

    def overlaps(self, other: SignalRef) -> bool:
        return (
            self.task == other.task
            and self.side == other.side
            and self.start < other.stop
            and other.start < self.stop
        )

    def __str__(self) -> str:
        if self.size == 1:
            return f"{self.task}.{self.side}[{self.start}]"
        return f"{self.task}.{self.side}[{self.start}:{self.stop}]"


class SentName(str):
    """A recorded column that names itself whole (``motor.voltage_V``: what device ``motor`` was
    sent), not after the task that records it."""

    __slots__ = ()


class SignalVector:
    """``task.u`` or ``task.y``: index or slice it to get a :class:`SignalRef`."""

    def __init__(self, task: str, side: Side, length: int) -> None:
        self.task, self.side, self.length = task, side, length

    def __getitem__(self, index: int | slice) -> SignalRef:
        kind = "input" if self.side == "u" else "output"
        if isinstance(index, int):
            if not 0 <= index < self.length:
                hint = f" (declare n_{kind}s on its Runnable class)" if self.length == 0 else ""
                raise AppError(
                    f"{self.task}.{self.side}[{index}]: index out of range; "
                    f"task {self.task!r} has {self.length} {kind}s{hint}"
                )
            return SignalRef(self.task, self.side, index, index + 1)
        start, stop, step = index.indices(self.length)
        if step != 1 or stop <= start or (index.stop is not None and index.stop > self.length):
            raise AppError(
                f"{self.task}.{self.side}[{index.start}:{index.stop}]: not a contiguous, non-empty "
                f"slice of {self.length} {kind}s"
            )
        return SignalRef(self.task, self.side, start, stop)

    @property
    def all(self) -> SignalRef:
        return SignalRef(self.task, self.side, 0, self.length)


@dataclass(slots=True)
class TaskSpec:
    """A task as added to the app (config + its runnable, before it runs)."""

    config: TaskConfig
    runnable: Runnable

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def u(self) -> SignalVector:
        return SignalVector(self.name, "u", self.runnable.n_inputs)

    @property
    def y(self) -> SignalVector:
        return SignalVector(self.name, "y", self.runnable.n_outputs)


@dataclass(slots=True)
class DeviceSpec:
    """A device as added to the app: its driver, the task whose process runs it, its limits."""

    device: Device
    task: str
    """The task that owns it: the device runs in that task's process, at its period."""
    io: str = "let"
    """``let``: commands of the job released at t are written at t + P; ``immediate``: after step."""
    limits: tuple[CommandLimit, ...] = ()
    """One per command (``u``), in order."""
    twin: Runnable | None = None
    """The model that answers as the device does (``rtloop simulate`` runs it in its place)."""

    @property
    def name(self) -> str:
        return self.device.name

    @property
    def u(self) -> SignalVector:
        return SignalVector(self.name, "u", self.device.n_inputs)

    @property
    def y(self) -> SignalVector:
        return SignalVector(self.name, "y", self.device.n_outputs)


@dataclass(frozen=True, slots=True)
class Connection:
    source: SignalRef
    target: SignalRef
    allow_nonfinite: bool = False
    """Let NaN and ±inf cross (counted and named in the summary); otherwise they are a fault."""
    min: float = -math.inf
    """The guard (``app/guards.py``): the reader gets values clamped to ``[min, max]``..."""
    max: float = math.inf
    rate_per_s: float = math.inf
    """...moving by at most this much per second (inf: no limit)."""

    @property
    def guarded(self) -> bool:
        return self.min > -math.inf or self.max < math.inf or self.rate_per_s < math.inf


ValueRange = tuple[float, float] | tuple[tuple[float, ...], tuple[float, ...]]
"""A port's ``(lo, hi)``: two numbers for all its values, or two tuples with one number per value."""


@dataclass(frozen=True, slots=True)
class PortSpec:
    """A named endpoint between the app and non-real-time code."""

    name: str
    direction: Literal["in", "out"]
    signal: SignalRef
    initial: tuple[float, ...] | None = None
    allow_nonfinite: bool = False
    capacity: int = 4096
    feed: Path | None = None
    value_range: ValueRange | None = None
    """``[lo, hi]`` (or one pair per value): values written to an input port outside it are refused (like NaN)."""
    nudge: str | None = None
    """A port fed from a profile takes live writes too: ``offset`` (the task sees the profile
    plus the latest value written) or ``override`` (a write holds until the profile's next row)."""


NUDGE_MODES = ("offset", "override")


@dataclass(frozen=True, slots=True)
class RosTopic:
    """A ROS 2 topic bridged to a port, in a non-real-time bridge process started with the app."""

    direction: Literal["publish", "subscribe"]
    """``publish``: an output port's values go out on the topic; ``subscribe``: the topic feeds an input port."""
    topic: str
    """ROS 2 topic name, e.g. ``/jiwy/angles`` (on DDS: ``rt/jiwy/angles``)."""
    port: str
    """The app port it is attached to."""
    msg_type: str = "std_msgs/msg/Float64MultiArray"
    """One of :data:`ROS_TYPES`."""
    qos: str = "reliable"
    """``reliable`` (ROS 2's default: keep last 10; matches every reader) or ``sensor`` (best effort, keep last 5)."""
    joint_names: tuple[str, ...] = ()
    """For ``sensor_msgs/msg/JointState``: one name per value."""
    every: int = 1
    """Publish every N-th tick only (a 1 kHz task need not flood rviz)."""
    domain_id: int | None = None
    """DDS domain; ``None``: ``ROS_DOMAIN_ID`` or 0."""
    value_range: ValueRange | None = None
    """``subscribe`` only: messages with a value outside ``[lo, hi]`` are rejected and counted."""


@dataclass(frozen=True, slots=True)
class LiveViewSpec:
    """A Foxglove WebSocket server (``foxglove.sdk.v1`` or ``foxglove.websocket.v1``) showing the run live."""

    host: str = "127.0.0.1"
    """Address to bind: this machine only unless told otherwise (``0.0.0.0``: every interface)."""
    port: int = 8765
    """TCP port; 0 picks a free one (the run prints the URL)."""
    inputs: tuple[str, ...] = ()
    """Input ports Foxglove may write (topic ``/rtloop/ports/<port>``), checked as the talker checks."""


def check_twin(name: str, source: str, device: Device, twin: object) -> None:
    if not isinstance(twin, Runnable):
        raise DeviceError(name, source, "twin", f"{shorten(twin)} is not an rtloop.Runnable")
    if (twin.n_inputs, twin.n_outputs) != (device.n_inputs, device.n_outputs):
        raise DeviceError(name, source, "twin", f"{type(twin).__name__} has {twin.n_inputs} inputs and "
                          f"{twin.n_outputs} outputs; the device writes {device.n_inputs} and reads "
                          f"{device.n_outputs} (a twin takes the commands and answers the readings)")


LIMIT_KEYS = ("min", "max", "safe", "rate_per_s")


def resolve_limits(name: str, source: str, device: Device,
                    given: dict[str, CommandLimit | dict[str, float]]) -> tuple[CommandLimit, ...]:
    """One CommandLimit per command: the app's, else the driver's default; a safe value for each."""
    commands = device.command_names()
    if not isinstance(given, dict):
        raise DeviceError(name, source, "limits", f"expected a table of commands {list(commands)}")
    limits = dict(device.default_limits())
    for command, limit in given.items():
        key = f"limits.{clip(str(command), 40)}"
        if command not in commands:
            raise DeviceError(name, source, key, f"no such command; the device writes {list(commands)}")
        if isinstance(limit, dict):
            unknown = sorted(set(limit) - set(LIMIT_KEYS))
            if unknown:
                raise DeviceError(name, source, f"{key}.{clip(str(unknown[0]), 40)}",
                                  f"unknown key; expected {list(LIMIT_KEYS)}")
            missing = [k for k in ("min", "max", "safe") if k not in limit]
            if missing:
                raise DeviceError(name, source, f"{key}.{missing[0]}", "missing; a command needs min, max and safe")
            limit = CommandLimit(limit["min"], limit["max"], limit["safe"], limit.get("rate_per_s", math.inf))
        if not isinstance(limit, CommandLimit):
            raise DeviceError(name, source, key, f"expected a table with {list(LIMIT_KEYS)}, got {shorten(limit)}")
        problem = limit.problem()
        if problem:
            raise DeviceError(name, source, key, problem)
        limits[command] = limit
    missing_commands = [c for c in commands if c not in limits]
    if missing_commands:
        raise DeviceError(name, source, f"limits.{missing_commands[0]}",
                          "missing; every command needs min, max and a safe value (written when the run ends)")
    return tuple(limits[c] for c in commands)


def too_many_tasks(count: int) -> str:
    """The refusal of an app of ``count`` tasks (more than :data:`MAX_TASKS`)."""
    return (f"{count} tasks; an app has at most {MAX_TASKS} (each task is a process that locks its memory): "
            "let one task step several runnables, or split the app")


def check_duration(duration_s: float) -> float:
    """A run's length: a finite number of seconds, more than 0 and at most :data:`MAX_DURATION_S`."""
    if isinstance(duration_s, bool) or not isinstance(duration_s, int | float) \
            or not 0 < duration_s <= MAX_DURATION_S:
        raise AppError(f"duration must be more than 0 and at most {MAX_DURATION_S:g} seconds, "
                       f"got {shorten(duration_s)}")
    return float(duration_s)


def check_number(what: str, key: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise AppError(f"{what}: {key} must hold numbers, got {shorten(value)}")
    try:
        return float(value)
    except OverflowError:
        raise AppError(f"{what}: {key} value {shorten(value)} does not fit a float64") from None


def check_range(what: str, value_range: object, size: int | None = None) -> ValueRange | None:
    """``[lo, hi]`` for every value, or (a port of ``size`` values) ``[[lo, hi], ...]``, one pair per
    value: a port of gains in different units needs a bound of its own for each."""
    if value_range is None:
        return None
    if size is not None and isinstance(value_range, list | tuple) and value_range \
            and all(isinstance(pair, list | tuple) for pair in value_range):
        if len(value_range) != size:
            raise AppError(f"{what}: range has {len(value_range)} [lo, hi] pairs, the port has {size} values")
        pairs = [check_pair(f"{what}: range[{index}]", pair) for index, pair in enumerate(value_range)]
        return tuple(pair[0] for pair in pairs), tuple(pair[1] for pair in pairs)
    return check_pair(what, value_range, " or one [lo, hi] per value" if size is not None and size > 1 else "")


def check_pair(what: str, value_range: object, one_per_value: str = "") -> tuple[float, float]:
    """One ``[lo, hi]``: two finite numbers, lo ≤ hi."""
    if not isinstance(value_range, list | tuple) or len(value_range) != 2:
        raise AppError(f"{what}: range must be [lo, hi]{one_per_value}, got {shorten(value_range)}")
    low, high = (check_number(what, "range", v) for v in value_range)
    if not (math.isfinite(low) and math.isfinite(high) and low <= high):
        raise AppError(f"{what}: range [{low!r}, {high!r}] must be finite with lo ≤ hi")
    return low, high


def range_of_value(value_range: ValueRange, index: int) -> tuple[float, float]:
    """The ``(lo, hi)`` that value ``index`` of a port must lie in."""
    low, high = value_range
    return (low[index] if isinstance(low, tuple) else low, high[index] if isinstance(high, tuple) else high)


def check_cpu(where: str, cpu: int | None, policy: str) -> None:
    """A CPU this process may run on, and not for SCHED_DEADLINE (the kernel refuses to pin those)."""
    if cpu is None:
        return
    available = sorted(os.sched_getaffinity(0))
    if not isinstance(cpu, int) or cpu not in available:
        raise AppError(f"{where}: cpu {cpu!r} is not one of this machine's CPUs {available}")
    if policy == "deadline":
        raise AppError(f"{where}: a SCHED_DEADLINE task cannot be pinned to one CPU (the kernel refuses); "
                       "leave cpu unset, or use fifo/rr to pin it")
