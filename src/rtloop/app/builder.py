"""The app builder: tasks, connections, ports and recordings, checked as they are added.

    app = App("jiwy")
    plant = app.add_task("plant", JiwyPlant(), period_ns=1_000_000, priority=80, cpu=1)
    controller = app.add_task("controller", JiwyController(), period_ns=1_000_000, cpu=1)
    app.connect(plant.y[0:2], controller.u[0:2])
    app.connect(controller.y[0:2], plant.u[0:2])
    app.port("setpoint", to=controller.u[2:4])
    app.record(plant.y, controller.y)
    summary = rtloop.run(app, duration_s=10, out="runs/jiwy")

Every mistake that can be found before a process starts is found here, with an
:class:`~rtloop.errors.AppError` that names the culprit.
"""

from __future__ import annotations

import dataclasses
import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from rtloop.app.byvalue import dumps_runnable
from rtloop.app.guards import guarded_connection, record_device_link
from rtloop.app.hints import reissue_at_user, signal_hint
from rtloop.app.plots import PlotSpec, check_unit
from rtloop.app.profiles import check_profile_file
from rtloop.app.specs import (
    DEFAULT_WATCHDOG_PERIODS,
    MAX_PERIOD_NS,
    MAX_PORT_CAPACITY,
    MAX_TASKS,
    MAX_VECTOR_SIZE,
    MIN_PERIOD_NS,
    NAME_PATTERN,
    NUDGE_MODES,
    OVERRUN_POLICIES,
    Connection,
    DeviceSpec,
    LiveViewSpec,
    PortSpec,
    RosTopic,
    SignalRef,
    SignalVector,
    TaskConfig,
    TaskSpec,
    check_cpu,
    check_number,
    check_range,
    check_twin,
    range_of_value,
    resolve_limits,
    too_many_tasks,
)
from rtloop.app.step_check import warn_about_step
from rtloop.errors import AppError, ConnectionSizeError, DeviceError
from rtloop.io.device import IO_MODES, CommandLimit, Device, build_device, check_claims
from rtloop.ros.types import ROS_TYPES
from rtloop.runnable import Runnable
from rtloop.switching import Controllers, switch_port_name
from rtloop.text import shorten


@dataclass
class App:
    """Periodic tasks and their wiring, described; ``rtloop.run(app)`` or ``rtloop.simulate(app)`` runs it."""

    name: str
    tasks: dict[str, TaskSpec] = field(default_factory=dict)
    connections: list[Connection] = field(default_factory=list)
    ports: dict[str, PortSpec] = field(default_factory=dict)
    recorded: list[SignalRef] = field(default_factory=list)
    ros_topics: list[RosTopic] = field(default_factory=list)
    live_view: LiveViewSpec | None = None
    devices: dict[str, DeviceSpec] = field(default_factory=dict)
    device_links: list[Connection] = field(default_factory=list)
    """Connections between a device and the task that owns it (in that task's process)."""
    plots: list[PlotSpec] = field(default_factory=list)
    """Signals the report draws on one axis (``app.plot``); setpoint/measured pairs are also inferred."""
    unit_overrides: dict[tuple[str, str, int], str] = field(default_factory=dict)
    """(task, side, index) → unit, declared by the app (``app.set_units``) over the runnable's own."""
    source: str = "<python>"
    """Where the app was described (an app file's path, for messages)."""
    sources: dict[str, str] = field(default_factory=dict)
    """The files it was made of (app file, modules, models), path → digest (``app/sources.py``)."""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not NAME_PATTERN.match(self.name):
            raise AppError(f"app name {shorten(self.name)}: use letters, digits and underscores, at most 32")

    # --- building ------------------------------------------------------------------------
    def add_task(
        self,
        name: str,
        runnable: Runnable,
        *,
        period_ns: int,
        priority: int = 80,
        cpu: int | None = None,
        policy: str = "fifo",
        overrun: str = "skip",
        watchdog_periods: int = DEFAULT_WATCHDOG_PERIODS,
        max_consecutive_misses: int | None = None,
        lock_blas_buffer: bool = False,
    ) -> TaskSpec:
        """Add a periodic task running ``runnable`` every ``period_ns``; returns its handle."""
        where = f"task {name!r}"
        if not isinstance(name, str) or not NAME_PATTERN.match(name):
            raise AppError(f"task {shorten(name)}: a task name uses letters, digits and underscores, at most 32")
        if name in self.tasks:
            raise AppError(f"{where}: defined twice")
        if len(self.tasks) >= MAX_TASKS:
            raise AppError(too_many_tasks(len(self.tasks) + 1))
        if not isinstance(runnable, Runnable):
            raise AppError(f"{where}: {runnable!r} is not an rtloop.Runnable")
        if not isinstance(period_ns, int) or isinstance(period_ns, bool) \
                or not MIN_PERIOD_NS <= period_ns <= MAX_PERIOD_NS:
            raise AppError(f"{where}: period_ns must be an integer from {MIN_PERIOD_NS} (100 kHz) to "
                           f"{MAX_PERIOD_NS} (1 hour), got {shorten(period_ns)}")
        if policy not in ("fifo", "rr", "other", "deadline"):
            raise AppError(f"{where}: policy {policy!r}; expected fifo, rr, other or deadline")
        low = 0 if policy in ("other", "deadline") else 1
        if not isinstance(priority, int) or not low <= priority <= 99:
            raise AppError(f"{where}: priority {priority!r}; expected an integer {low}–99 for {policy}")
        if policy in ("other", "deadline"):
            priority = 0
        check_cpu(where, cpu, policy)
        if overrun not in OVERRUN_POLICIES:
            raise AppError(f"{where}: overrun {overrun!r}; expected one of {OVERRUN_POLICIES}")
        if not isinstance(watchdog_periods, int) or isinstance(watchdog_periods, bool) or watchdog_periods < 0:
            raise AppError(f"{where}: watchdog_periods {watchdog_periods!r}; expected an integer ≥ 0 (0: off)")
        if max_consecutive_misses is not None and (
            not isinstance(max_consecutive_misses, int) or isinstance(max_consecutive_misses, bool)
            or max_consecutive_misses < 1
        ):
            raise AppError(f"{where}: max_consecutive_misses {max_consecutive_misses!r}; "
                           "expected an integer ≥ 1 (or none: count misses and go on)")
        if not isinstance(lock_blas_buffer, bool):
            raise AppError(f"{where}: lock_blas_buffer must be true or false, got {shorten(lock_blas_buffer)}")
        runnable.add_parameter_inputs()  # live parameters become inputs after the declared ones
        for side, count in (("n_inputs", runnable.n_inputs), ("n_outputs", runnable.n_outputs)):
            if not isinstance(count, int) or isinstance(count, bool) or not 0 <= count <= MAX_VECTOR_SIZE:
                raise AppError(f"{where}: {type(runnable).__name__}.{side} must be an integer from 0 to "
                               f"{MAX_VECTOR_SIZE}, got {shorten(count)}")
        check_period = getattr(runnable, "check_period", None)
        if callable(check_period):
            with warnings.catch_warnings(record=True) as caught:  # said again at the user's line, not ours
                warnings.simplefilter("always")
                check_period(period_ns)
            reissue_at_user(caught, self.source, name)
        warn_about_step(name, runnable)  # `return y` or `y = ...` in step: outputs that never leave 0
        config = TaskConfig(name, period_ns, priority, cpu, policy, overrun, watchdog_periods,
                            max_consecutive_misses, lock_blas_buffer)
        spec = TaskSpec(config, runnable)
        self.tasks[name] = spec
        if isinstance(runnable, Controllers):  # its switch port (what `rtloop switch` writes); all it does recorded
            at = runnable.switch_slice
            self.port(switch_port_name(name), to=spec.u[at.start:at.stop], value_range=runnable.switch_ranges())
            self.record(spec.y)
        return spec

    def pin_all(self, cpu: int) -> None:
        """Pin every task to ``cpu`` (e.g. the isolated core of a Raspberry Pi)."""
        for spec in self.tasks.values():
            check_cpu(f"task {spec.name!r}", cpu, spec.config.policy)
        for spec in self.tasks.values():
            spec.config = dataclasses.replace(spec.config, cpu=cpu)

    def add_device(
        self,
        name: str,
        kind: str | type[Device] | Device,
        *,
        task: str,
        io: str = "let",
        twin: Runnable | None = None,
        limits: dict[str, CommandLimit | dict[str, float]] | None = None,
        **settings: object,
    ) -> DeviceSpec:
        """Add a device run by ``task``'s process; returns its handle (``.u`` commands, ``.y`` readings).

        ``kind``: ``"serial"``, ``"gpio"``, … (its ``settings`` as keyword arguments), a Device
        subclass, or a Device already built. ``limits``: per command name, ``CommandLimit`` or
        ``{"min":, "max":, "safe":, "rate_per_s":}``; every command needs min, max and safe.
        """
        source = self.source
        if not isinstance(name, str) or not NAME_PATTERN.match(name):
            raise AppError(f"device {shorten(name)}: a device name uses letters, digits and underscores, at most 32")
        if name in self.devices or name in self.tasks:
            raise DeviceError(name, source, "", "the name is taken (task and device names share one namespace)")
        if task not in self.tasks:
            raise DeviceError(name, source, "task", f"unknown task {shorten(task)}; tasks are {sorted(self.tasks)}")
        if io not in IO_MODES:
            raise DeviceError(name, source, "io", f"{shorten(io)}; expected one of {list(IO_MODES)}")
        if isinstance(kind, Device):
            if settings:
                raise DeviceError(name, source, "", "settings go to the Device's constructor when it is built already")
            if kind.name != name:
                raise DeviceError(name, source, "", f"the Device was built with the name {kind.name!r}")
            device = kind
        else:
            device = build_device(kind, name, settings, source)
        problem = device.period_problem(self.tasks[task].config.period_ns)
        if problem is not None:
            raise DeviceError(name, source, *problem)
        twin = device.default_twin() if twin is None else twin  # a servo bus brings its model, drives theirs
        if twin is not None:
            check_twin(name, source, device, twin)
        spec = DeviceSpec(device, task, io, resolve_limits(name, source, device, limits or {}), twin)
        check_claims([*(other.device for other in self.devices.values()), device], source)
        self.devices[name] = spec
        return spec

    def block(self, name: str) -> TaskSpec | DeviceSpec | None:
        """The task or device called ``name`` (both have ``.u`` and ``.y``)."""
        return self.tasks.get(name) or self.devices.get(name)

    def _resolve(self, signal: SignalRef | SignalVector, role: str, devices: bool = False) -> SignalRef:
        ref = signal.all if isinstance(signal, SignalVector) else signal
        if not isinstance(ref, SignalRef):
            raise AppError(f"{role}: expected a signal such as plant.y[0:2], got {signal!r}")
        if ref.task in self.devices and not devices:
            raise AppError(f"{role} {ref}: {ref.task!r} is a device; only connections reach devices "
                           "(use the task signals it is connected to)")
        if ref.task not in self.tasks and ref.task not in self.devices:
            raise AppError(f"{role} {ref}: unknown task {ref.task!r}; tasks are {sorted(self.tasks)}")
        return ref

    def _check_single_writer(self, target: SignalRef, what: str) -> None:
        for existing in self.connections + self.device_links:
            if existing.target.overlaps(target):
                raise AppError(
                    f"{what}: {target} already receives {existing.source} → {existing.target}; "
                    "an input has at most one writer"
                )
        for port in self.ports.values():
            if port.direction == "in" and port.signal.overlaps(target):
                raise AppError(
                    f"{what}: {target} is already fed by port {port.name!r} ({port.signal}); "
                    "an input has at most one writer"
                )

    def connect(self, source: SignalRef | SignalVector, target: SignalRef | SignalVector, *,
                allow_nonfinite: bool = False, min: float | None = None, max: float | None = None,
                rate_per_s: float | None = None) -> Connection:
        """Wire an output slice (``y``) to an input slice (``u``) of the same size.

        A NaN or ±inf crossing it is a fault naming task, cycle and output, unless ``allow_nonfinite``:
        then it crosses, counted and named. ``min``, ``max``, ``rate_per_s``: a guard (``app/guards.py``).

        Either end may be a device, wired to the task that owns it: ``motor.y[0]`` (a reading)
        → ``controller.u[1]``, ``controller.y[0]`` → ``motor.u[0]`` (a command).
        """
        src = self._resolve(source, "connect from", devices=True)
        dst = self._resolve(target, "connect to", devices=True)
        what = f"connect {src} → {dst}"
        if src.side != "y":
            raise AppError(f"{what}: the source must be an output (y), not {src.side}")
        if dst.side != "u":
            raise AppError(f"{what}: the target must be an input (u), not {dst.side}")
        if src.size != dst.size:
            raise ConnectionSizeError(f"{what}: {src} has {src.size} values but {dst} has {dst.size}")
        self._check_single_writer(dst, what)
        device = self.devices.get(src.task) or self.devices.get(dst.task)
        connection = guarded_connection(what, src, dst, bool(allow_nonfinite), (min, max, rate_per_s), device)
        if device is None:
            self.connections.append(connection)
            return connection
        other = dst.task if device.name == src.task else src.task
        if other != device.task:
            raise AppError(f"{what}: device {device.name!r} runs in task {device.task!r}'s process and is wired "
                           f"to that task only; route {other!r}'s signals through {device.task!r}")
        self.device_links.append(connection)
        record_device_link(self, connection, device.name)  # its reading, or what it was sent
        return connection

    def port(
        self,
        name: str,
        *,
        to: SignalRef | SignalVector | None = None,
        source: SignalRef | SignalVector | None = None,
        initial: list[float] | None = None,
        allow_nonfinite: bool = False,
        capacity: int = 4096,
        feed: str | Path | None = None,
        value_range: tuple[float, float] | list[float] | list[list[float]] | None = None,
        nudge: str | None = None,
        range: tuple[float, float] | list[float] | list[list[float]] | None = None,  # the app file's key too
    ) -> PortSpec:
        """A port into a task (``to=``, latest value) or out of one (``source=``, every tick).

        Input ports: ``initial=[...]`` is what the task reads until the first write (default:
        zeros, or a model's input start values). ``feed="profile.csv"`` plays a profile into
        it (``t_s`` then one column per value, each row held until the next: zero-order
        hold); live writes are then refused unless ``nudge="offset"`` (the task reads the
        row plus the latest value written, 0 until then) or ``nudge="override"`` (a write
        holds until the next row starts). ``value_range=(lo, hi)`` (``range`` in an app file),
        or one ``(lo, hi)`` per value (``[[0, 0.5], [0, 50]]``): values written from outside that
        fall outside it are refused and counted, like NaN; ``range=`` is accepted as the same.
        """
        what = f"port {shorten(name)}"
        if range is not None:
            if value_range is not None:
                raise AppError(f"{what}: give range= or value_range= (the same), not both")
            value_range = range
        if not isinstance(name, str) or not NAME_PATTERN.match(name):
            raise AppError(f"{what}: a port name uses letters, digits and underscores, at most 32")
        if name in self.ports:
            raise AppError(f"{what}: defined twice")
        if (to is None) == (source is None):
            raise AppError(f"{what}: give exactly one of to= (into a task) or source= (out of a task)")
        if to is not None:
            ref = self._resolve(to, what)
            if ref.side != "u":
                raise AppError(f"{what}: to={ref} must be a task input (u)")
            self._check_single_writer(ref, what)
            initial_values = None
            checked_range = check_range(what, value_range, ref.size)
            if initial is not None:
                if len(initial) != ref.size:
                    raise ConnectionSizeError(f"{what}: initial has {len(initial)} values, {ref} has {ref.size}")
                initial_values = tuple(check_number(what, "initial", v) for v in initial)
                if not allow_nonfinite and not all(math.isfinite(v) for v in initial_values):
                    raise AppError(f"{what}: initial {shorten(list(initial_values))} holds NaN or inf: the task would "
                                   "read it at cycle 0 (allow_nonfinite = true on the port lets it through)")
                bounds = [range_of_value(checked_range, i) for i, _ in enumerate(initial_values)] \
                    if checked_range else []
                for index, (value, (low, high)) in enumerate(zip(initial_values, bounds, strict=False)):
                    if not low <= value <= high:
                        raise AppError(f"{what}: initial {shorten(list(initial_values))} is outside its range: "
                                       f"value {index} must lie in [{low!r}, {high!r}]")
            if nudge is not None and nudge not in NUDGE_MODES:
                raise AppError(f"{what}: nudge {shorten(nudge)}; expected one of {list(NUDGE_MODES)}")
            if feed is not None:
                check_profile_file(feed, what)
            spec = PortSpec(name, "in", ref, initial_values, allow_nonfinite, capacity,
                            Path(feed) if feed is not None else None, checked_range, nudge)
        else:
            assert source is not None
            ref = self._resolve(source, what)
            if ref.side != "y":
                raise AppError(f"{what}: source={ref} must be a task output (y)")
            if feed is not None:
                raise AppError(f"{what}: only ports into a task can be fed from a profile")
            if value_range is not None:
                raise AppError(f"{what}: range applies to ports into a task (values from outside)")
            if nudge is not None:
                raise AppError(f"{what}: nudge applies to ports into a task fed from a profile")
            if not isinstance(capacity, int) or isinstance(capacity, bool) or not 2 <= capacity <= MAX_PORT_CAPACITY:
                raise AppError(f"{what}: capacity must be an integer from 2 to {MAX_PORT_CAPACITY}, "
                               f"got {shorten(capacity)}")
            spec = PortSpec(name, "out", ref, capacity=capacity)
        self.ports[name] = spec
        return spec

    def feed(self, port: str, csv_path: str | Path) -> None:
        """Feed an input port from a CSV profile (``t_s`` then one column per value)."""
        if port not in self.ports or self.ports[port].direction != "in":
            inputs = sorted(n for n, p in self.ports.items() if p.direction == "in")
            raise AppError(f"feed {port}={csv_path}: no input port {port!r}; input ports are {inputs}")
        check_profile_file(csv_path, f"port {port!r}")
        self.ports[port] = dataclasses.replace(self.ports[port], feed=Path(csv_path))

    def ros_publish(self, topic: str, *, source: SignalRef | SignalVector | None = None, port: str | None = None,
                    msg_type: str = "std_msgs/msg/Float64MultiArray", qos: str = "reliable",
                    joint_names: list[str] | tuple[str, ...] = (), every: int = 1,
                    domain_id: int | None = None) -> RosTopic:
        """Publish task outputs on a ROS 2 topic while the app runs.

        Give ``source=`` (a signal: a port of its own is made for the bridge) or ``port=``
        (an existing output port, which the bridge then reads exclusively).
        """
        if (source is None) == (port is None):
            raise AppError(f"ros publish {topic!r}: give exactly one of source= (a signal) or port= (an output port)")
        if source is not None:
            port = "ros_" + re.sub(r"\W", "_", topic.strip("/"))
            self.port(port, source=source)
        assert port is not None
        return self._ros("publish", topic, port, msg_type, qos, tuple(joint_names), every, domain_id)

    def ros_subscribe(self, topic: str, *, port: str, msg_type: str = "std_msgs/msg/Float64MultiArray",
                      qos: str = "reliable", domain_id: int | None = None,
                      value_range: tuple[float, float] | list[float] | None = None) -> RosTopic:
        """Feed an input port from a ROS 2 topic while the app runs (bad messages are rejected and counted).

        ``value_range=(lo, hi)``: messages with a value outside it are rejected and counted, like NaN
        (the port's own range, if any, applies too).
        """
        checked = check_range(f"ros subscribe {shorten(topic)}", value_range)
        topic_spec = self._ros("subscribe", topic, port, msg_type, qos, (), 1, domain_id)
        if checked is not None:
            self.ros_topics[-1] = topic_spec = dataclasses.replace(topic_spec, value_range=checked)
        return topic_spec

    def _ros(self, direction: Literal["publish", "subscribe"], topic: str, port: str, msg_type: str, qos: str,
             joint_names: tuple[str, ...], every: int, domain_id: int | None) -> RosTopic:
        what = f"ros {direction} {topic!r}"
        wanted = "out" if direction == "publish" else "in"
        spec = self.ports.get(port)
        if spec is None or spec.direction != wanted:
            candidates = sorted(n for n, p in self.ports.items() if p.direction == wanted)
            kind = "output" if wanted == "out" else "input"
            raise AppError(f"{what}: no {kind} port {port!r}; {kind} ports are {candidates}")
        if not re.fullmatch(r"/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*", topic):
            raise AppError(f"{what}: not a valid ROS 2 topic name (e.g. /jiwy/angles)")
        if msg_type not in ROS_TYPES:
            raise AppError(f"{what}: type {msg_type!r}; expected one of {list(ROS_TYPES)}")
        if msg_type == "std_msgs/msg/Float64" and spec.signal.size != 1:
            raise ConnectionSizeError(f"{what}: std_msgs/msg/Float64 carries 1 value, port {port!r} has "
                                      f"{spec.signal.size}")
        if joint_names and len(joint_names) != spec.signal.size:
            raise ConnectionSizeError(f"{what}: {len(joint_names)} joint names for {spec.signal.size} values")
        if qos not in ("sensor", "reliable"):
            raise AppError(f"{what}: qos {qos!r}; expected 'sensor' or 'reliable'")
        if not isinstance(every, int) or every < 1:
            raise AppError(f"{what}: every must be an integer ≥ 1")
        if any(t.topic.strip("/") == topic.strip("/") and t.direction == direction for t in self.ros_topics):
            raise AppError(f"{what}: defined twice")
        ros_topic = RosTopic(direction, topic, port, msg_type, qos, joint_names, every, domain_id)
        self.ros_topics.append(ros_topic)
        return ros_topic

    def serve_foxglove(self, port: int = 8765, *, host: str = "127.0.0.1",
                       inputs: list[str] | tuple[str, ...] = ()) -> LiveViewSpec:
        """Serve the recorded signals and each task's timing live to Foxglove while the app runs.

        ``inputs`` names the input ports Foxglove may publish to (none by default).
        """
        what = f"foxglove {host}:{port}"
        if not isinstance(port, int) or isinstance(port, bool) or not 0 <= port <= 65535:
            raise AppError(f"{what}: port must be an integer 0..65535 (0: any free port)")
        if not isinstance(host, str) or not host or any(c.isspace() for c in host):
            raise AppError(f"{what}: host must be an address such as 127.0.0.1")
        for name in inputs:
            if name not in self.ports or self.ports[name].direction != "in":
                candidates = sorted(n for n, p in self.ports.items() if p.direction == "in")
                raise AppError(f"{what}: inputs: no input port {name!r}; input ports are {candidates}")
        self.live_view = LiveViewSpec(host, port, tuple(inputs))
        return self.live_view

    def record(self, *signals: SignalRef | SignalVector) -> None:
        """Record these signals every tick into ``signals.csv`` and ``run.mcap``."""
        for signal in signals:
            ref = self._resolve(signal, "record")
            taken = {i for r in self.recorded if (r.task, r.side) == (ref.task, ref.side)
                     for i in range(r.start, r.stop)}
            start = None  # each element once: a signal named twice (plant.y and plant.AnglePan) is one column
            for index in range(ref.start, ref.stop + 1):
                free = index < ref.stop and index not in taken
                if free and start is None:
                    start = index
                elif not free and start is not None:
                    self.recorded.append(SignalRef(ref.task, ref.side, start, index))
                    start = None

    def plot(self, *signals: SignalRef | SignalVector, title: str = "") -> PlotSpec:
        """Draw these signals on one axis of the report (e.g. a setpoint over what it sets)."""
        what = f"plot {shorten(title)}" if title else "plot"
        if not isinstance(title, str) or len(title) > 120 or not title.isprintable():
            raise AppError(f"{what}: title must be printable text of at most 120 characters")
        if not signals:
            raise AppError(f"{what}: name at least one signal")
        refs = tuple(self._resolve(signal, what) for signal in signals)
        spec = PlotSpec(title, refs)
        self.plots.append(spec)
        return spec

    def set_units(self, task: str, units: dict[str, str]) -> None:
        """Units of a task's signals, by name or index: ``{"AnglePan": "rad", "u[0]": "V"}``.

        They take precedence over what the runnable or model declares.
        """
        if task not in self.tasks:
            raise AppError(f"units of {shorten(task)}: unknown task; tasks are {sorted(self.tasks)}")
        if not isinstance(units, dict):
            raise AppError(f"units of task {task!r}: expected a table of signal name → unit")
        for key, unit in units.items():
            ref = parse_signal(f"{task}.{key}", self, f"units of task {task!r}")
            checked = check_unit(f"units of {task}.{key}", unit)
            for index in range(ref.start, ref.stop):
                self.unit_overrides[(task, ref.side, index)] = checked

    # --- checking ------------------------------------------------------------------------
    def validate(self) -> None:
        """Checks that need the whole app (done again before running)."""
        if not self.tasks:
            raise AppError(f"app {self.name!r} ({self.source}) has no tasks")
        for name, spec in self.tasks.items():
            dumps_runnable(spec.runnable, name)  # it can reach its task process (or one line says why not)
        for port in self.ports.values():
            if port.nudge is not None and port.feed is None:
                raise AppError(f"port {port.name!r}: nudge = {port.nudge!r} adds live writes to a profile, but no "
                               f"profile feeds it (feed = \"FILE.csv\", or --feed {port.name}=FILE.csv)")
        for name, device in self.devices.items():
            try:
                dumps_runnable((device.device, device.twin), device.task)  # by value, as the task's runnable
            except Exception as error:
                raise DeviceError(name, self.source, "", f"cannot be sent to task {device.task!r}'s process "
                                  f"({error}); a driver opens its interface in configure(), not __init__") from None


def parse_signal(text: str, app: App, where: str) -> SignalRef:
    """Parse ``task.y[0:2]``, ``task.u[3]`` or ``task.y`` against an app's tasks."""
    match = re.fullmatch(r"\s*([A-Za-z_]\w*)\.([uy])(?:\[(\d{0,9})(?::(\d{0,9}))?\])?\s*", text)
    if not match:
        named = _named_signal(text, app)
        if named is not None:
            return named
        raise AppError(f"{where}: {shorten(text)} is not a signal{signal_hint(text, app)}; "
                       "expected e.g. 'plant.y[0:2]' or 'controller.u[3]'")
    task, side, start, stop = match.groups()
    block = app.block(task)
    if block is None:
        raise AppError(f"{where}: {shorten(text)} names unknown task {shorten(task)}{signal_hint(text, app)}; "
                       f"tasks are {sorted(app.tasks)}")
    vector = block.y if side == "y" else block.u
    if start is None:
        return vector.all
    if stop is None and ":" not in text:
        return vector[int(start)]
    return vector[slice(int(start) if start else None, int(stop) if stop else None)]


def _named_signal(text: str, app: App) -> SignalRef | None:
    """``plant.AnglePan``: one element named by the task's model (output names first)."""
    task, dot, name = text.strip().partition(".")
    spec = app.block(task)
    if not dot or not name or spec is None:
        return None
    named = spec.runnable if isinstance(spec, TaskSpec) else spec.device
    for side in ("y", "u"):
        names = list(getattr(named, "output_names" if side == "y" else "input_names", None) or ())
        if names.count(name) == 1:
            return (spec.y if side == "y" else spec.u)[names.index(name)]
    return None
