"""A run, live in Foxglove: the recorded signals and each task's timing over the Foxglove WebSocket protocol.

    rtloop run examples/jiwy/jiwy.toml --duration 60 --out runs/jiwy --foxglove 8765
    # Foxglove: Open connection → Foxglove WebSocket → ws://localhost:8765

The server (``foxglove-sdk``, ``pip install 'rtloop[live]'``) runs inside the supervisor,
a non-real-time process, on threads of its own. The supervisor hands over what it drains
anyway for the recordings; a thread here encodes and sends it. If that thread or a client
falls behind, the oldest batches are dropped (counted) — the tasks never notice.

Topics and messages are those of ``run.mcap``: ``/rtloop/signals`` (``JointState``, one
per tick, the signal names as joint names) and ``/rtloop/timing/<task>`` (``CycleTiming``).
Clients may offer the WebSocket subprotocol ``foxglove.sdk.v1`` or its older name
``foxglove.websocket.v1`` (Lichtblick, older Foxglove apps): see :mod:`rtloop.ros.subprotocol`.
Input ports listed in ``[foxglove] inputs`` take messages on ``/rtloop/ports/<port>``
(JSON ``{"data": [...]}`` as Foxglove's Publish panel sends a ``Float64MultiArray``, or
``{"position": [...]}``), checked exactly as the ROS 2 talker checks them.

**Live tuning.** The live parameters (``parameters = {"kp": 0.05}`` of a runnable) that an input
port listed in ``inputs`` feeds are served with the protocol's ``parameters`` capability, named
``task.parameter`` (``pi.kp``): Foxglove's and Lichtblick's Parameters panel reads and sets them
(``getParameters``/``setParameters``). A change is a write to that port (its ``range`` enforced,
``validate_values``' checks), so the task takes it at a release, logs it in inputs.csv and
``rtloop replay`` reproduces it. A refused value leaves the parameter as it was; the answer says
the value in force, and a status message says why.
"""

from __future__ import annotations

import json
import sys
import threading
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.app.builder import App
from rtloop.app.specs import LiveViewSpec
from rtloop.errors import PortValueError, RtloopError
from rtloop.ipc.ports import PortWriter, RunningApp, app_from_registry
from rtloop.record.live_parameters import LiveParameters
from rtloop.ros.cdr import cycle_timing_cdr, joint_state_cdr
from rtloop.ros.subprotocol import SubprotocolFront
from rtloop.ros.types import CYCLE_TIMING_SCHEMA, JOINT_STATE_SCHEMA, SIGNALS_TOPIC, TIMING_TOPIC_PREFIX, topic_token
from rtloop.ros.validate import MessageValidator, RateLimitedWarner

INPUT_TOPIC_PREFIX = "/rtloop/ports/"
MAX_PENDING_BATCHES = 200  # ~10 s of the supervisor's 50 ms drains


def served_to(host: str, inputs: tuple[str, ...] | list[str]) -> str:
    """What the console says of a live view served beyond this machine ('' for loopback only)."""
    if host in ("127.0.0.1", "::1", "localhost"):
        return ""
    where = "every network interface" if host in ("0.0.0.0", "::") else host
    writes = f" and may write port{'s' if len(inputs) > 1 else ''} {', '.join(inputs)}" if inputs else ""
    return f"; it listens on {where}: anyone on the network who reaches it sees the signals{writes}"

class LiveViewUnavailable(RtloopError, ImportError):
    """foxglove-sdk is not installed."""


class LiveViewError(RtloopError, OSError):
    """The live view's server could not start (address taken or invalid)."""


def import_foxglove() -> Any:
    try:
        import foxglove
    except ImportError:
        raise LiveViewUnavailable("the Foxglove live view needs foxglove-sdk: pip install 'rtloop[live]'") from None
    return foxglove


class LiveView:
    """The Foxglove server of one run; fed through :meth:`add_rows` and :meth:`add_timing` like run.mcap."""

    def __init__(self, app: App, spec: LiveViewSpec, signal_names: list[str], registry_path: Path) -> None:
        foxglove = import_foxglove()
        from foxglove.websocket import Capability

        self.app, self.spec, self.signal_names = app, spec, list(signal_names)
        self.context = foxglove.Context()  # ours alone: nothing else in the process logs into it

        def channel(topic: str, name: str, schema: str) -> Any:
            return foxglove.Channel(topic, schema=foxglove.Schema(name=name, encoding="ros2msg", data=schema.encode()),
                                    message_encoding="cdr", context=self.context)

        self.signals = channel(SIGNALS_TOPIC, "sensor_msgs/msg/JointState", JOINT_STATE_SCHEMA)
        self.timing = {task: channel(TIMING_TOPIC_PREFIX + topic_token(task), "rtloop_msgs/msg/CycleTiming",
                                     CYCLE_TIMING_SCHEMA) for task in app.tasks}
        self.inputs = _Inputs(app.name, spec.inputs, LiveParameters(app, spec.inputs))
        self.inputs.attach(app_from_registry(registry_path))  # ports exist already: writes may come before T0
        capabilities = [Capability.ClientPublish] if spec.inputs else []
        if self.inputs.parameters.served:
            capabilities.append(Capability.Parameters)
        try:  # clients reach it through the front below, which accepts both subprotocol names
            self.server = foxglove.start_server(
                name=f"rtloop {app.name}", host="127.0.0.1", port=0, context=self.context,
                capabilities=capabilities, server_listener=self.inputs, supported_encodings=["json"],
            )
        except Exception as error:  # foxglove raises its own error types
            raise LiveViewError(f"cannot start the Foxglove server: {error}") from None
        self.inputs.parameters.server = self.server
        try:
            self.front = SubprotocolFront(spec.host, spec.port, self.server.port)
        except OSError as error:
            self.server.stop()
            raise LiveViewError(f"cannot serve Foxglove on {spec.host}:{spec.port}: {error.strerror}") from None
        self.pending: deque[tuple[str, Any, Any]] = deque(maxlen=MAX_PENDING_BATCHES)
        self.offered = 0
        self.wake = threading.Event()
        self.closing = False
        self.t0_ns = self.wall_offset_ns = 0
        self.thread = threading.Thread(target=self._send_loop, name="rtloop-foxglove", daemon=True)

        host = "localhost" if spec.host in ("127.0.0.1", "0.0.0.0", "::", "::1") else spec.host
        self.url = f"ws://{host}:{self.front.port}"
        """Where Foxglove connects (the port the server got, if 0 was asked for)."""
        self.reach = served_to(spec.host, spec.inputs)
        """Who else can connect, for the console ('' on loopback only)."""

    def start(self, t0_ns: int, wall_t0_ns: int) -> None:
        """Begin sending: the epoch is known, so are the messages' times."""
        self.t0_ns, self.wall_offset_ns = t0_ns, wall_t0_ns - t0_ns
        self.thread.start()

    # --- fed by the supervisor (never blocks) ----------------------------------------------
    def add_rows(self, t_ns: np.ndarray, rows: np.ndarray) -> None:
        self._offer("signals", t_ns, rows)

    def add_timing(self, task: str, records: np.ndarray) -> None:
        self._offer(task, records, None)

    def _offer(self, kind: str, first: Any, second: Any) -> None:
        self.offered += 1
        self.pending.append((kind, first, second))  # full: the oldest batch goes
        self.wake.set()

    # --- the sending thread ------------------------------------------------------------------
    def _send_loop(self) -> None:
        while not self.closing:
            self.wake.wait(0.5)
            self.wake.clear()
            while self.pending:
                kind, first, second = self.pending.popleft()
                if kind == "signals":
                    self._send_rows(first, second)
                else:
                    self._send_timing(kind, first)

    def _send_rows(self, t_ns: np.ndarray, rows: np.ndarray) -> None:
        wall_t0_ns = self.t0_ns + self.wall_offset_ns
        for t, row in zip(np.asarray(t_ns).tolist(), np.asarray(rows).tolist(), strict=True):
            wall_ns = wall_t0_ns + t
            self.signals.log(joint_state_cdr(self.signal_names, row, wall_ns), log_time=wall_ns)

    def _send_timing(self, task: str, records: np.ndarray) -> None:
        channel = self.timing[task]
        for cycle, release, start, end in np.asarray(records, dtype=np.int64).reshape(-1, 4).tolist():
            channel.log(cycle_timing_cdr(cycle, release, start, end), log_time=release + self.wall_offset_ns)

    def close(self) -> None:
        self.closing = True
        self.wake.set()
        if self.thread.is_alive():
            self.thread.join(5.0)
        self.front.close()
        self.server.stop()
        self.inputs.parameters.close()
        self.inputs.close()

    def summary(self) -> dict[str, Any]:
        """What ``summary.json`` says about the live view (under ``bridges``)."""
        return {"foxglove": {"url": self.url, "batches_offered": self.offered, **self.inputs.counts()}}


class _Inputs:
    """Messages Foxglove publishes, to input ports, through the talker's checks (a foxglove ServerListener)."""

    def __init__(self, app_name: str, ports: tuple[str, ...], parameters: LiveParameters) -> None:
        self.app_name, self.ports, self.parameters = app_name, ports, parameters
        self.running: RunningApp | None = None
        self.writers: dict[str, PortWriter] = {}  # each input port mapped once, not at every message
        self.channels: dict[tuple[int, int], tuple[str, str]] = {}  # (client, channel) → (port, encoding)
        self.validators: dict[str, MessageValidator] = {}
        self.accepted = self.refused = self.undecodable = self.unknown_topic = 0
        self.lock = threading.Lock()
        self.warner = RateLimitedWarner(1.0, emit=lambda text: print(f"rtloop foxglove: {text}", file=sys.stderr,
                                                                       flush=True))

    def attach(self, running: RunningApp) -> None:
        for port in self.ports:
            info = running.ports[port]
            self.validators[port] = MessageValidator(
                int(info["size"]), allow_nonfinite=bool(info["allow_nonfinite"]),
                what=f"foxglove {INPUT_TOPIC_PREFIX}{port} → port {port}", warner=self.warner)
        self.writers = {port: running.writer(port) for port in self.ports}
        self.running = running
        self.parameters.attach(running, self.warner)

    def close(self) -> None:
        for writer in self.writers.values():
            writer.close()
        self.writers = {}

    def on_get_parameters(self, client: Any, param_names: list[str], request_id: str | None = None) -> list[Any]:
        return self.parameters.get(param_names)

    def on_set_parameters(self, client: Any, parameters: list[Any], request_id: str | None = None) -> list[Any]:
        return self.parameters.set(parameters)

    def on_client_advertise(self, client: Any, channel: Any) -> None:
        port = channel.topic.removeprefix(INPUT_TOPIC_PREFIX)
        if not channel.topic.startswith(INPUT_TOPIC_PREFIX) or port not in self.ports:
            with self.lock:
                self.unknown_topic += 1
            self.warner.warn(f"{channel.topic!r} is not an input topic; this app takes "
                             f"{[INPUT_TOPIC_PREFIX + p for p in self.ports]}", key="topic")
            return
        self.channels[(client.id, channel.id)] = (port, channel.encoding)

    def on_subscribe(self, client: Any, channel: Any) -> None:
        pass  # the server itself sends subscribed channels only

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        pass

    def on_client_unadvertise(self, client: Any, client_channel_id: int) -> None:
        self.channels.pop((client.id, client_channel_id), None)

    def on_message_data(self, client: Any, client_channel_id: int, data: bytes) -> None:
        target = self.channels.get((client.id, client_channel_id))
        if target is None or self.running is None:
            return
        port, encoding = target
        values = _values_of_json(data) if encoding == "json" else None
        if values is None:
            with self.lock:
                self.undecodable += 1
            self.warner.warn(f"{INPUT_TOPIC_PREFIX}{port}: expected JSON {{\"data\": [numbers]}}, got "
                             f"{encoding} {bytes(data[:60])!r}", key="decode")
            return
        checked = self.validators[port].check(values)
        if checked is None:
            return
        try:
            self.writers[port].write(checked)  # the server has stopped before close() lets them go
            with self.lock:
                self.accepted += 1
        except PortValueError as error:  # e.g. fed from a profile in this run
            with self.lock:
                self.refused += 1
            self.warner.warn(str(error), key="port")

    def counts(self) -> dict[str, Any]:
        by_reason: dict[str, int] = {}
        for validator in self.validators.values():
            for reason, count in validator.counts.rejected.items():
                by_reason[reason] = by_reason.get(reason, 0) + count
        return {**self.parameters.counts(), "inputs": list(self.ports), "input_written": self.accepted,
                "input_rejected": sum(by_reason.values()),
                "input_rejected_by_reason": by_reason, "input_refused_by_port": self.refused,
                "input_undecodable": self.undecodable, "input_unknown_topic": self.unknown_topic}


def _values_of_json(data: bytes) -> Any:
    try:
        message = json.loads(bytes(data))
    except (ValueError, UnicodeDecodeError):
        return None
    if not isinstance(message, dict):
        return None
    values = message.get("data", message.get("position"))
    return [values] if isinstance(values, int | float) and not isinstance(values, bool) else values
