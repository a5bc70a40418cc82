"""ROS 2 bridge nodes: the thesis's listener (RT data → topic) and talker (topic → RT).

Each bridge is a non-real-time process attached to a running app's port:

    rtloop bridge listener --app jiwy --port angles --topic /jiwy/angles --type sensor_msgs/msg/JointState \\
        --joint-names pan tilt
    rtloop bridge talker --app jiwy --topic /jiwy/setpoint --port setpoint

A listener publishes every tick an output port sends (or every N-th, ``--every``);
a talker checks every message (type, length, NaN/inf) before it reaches the port —
rejected ones are counted and warned about at most once a second. A bridge never
stalls the real-time side: ports drop and count when nobody reads them.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from rtloop.app.builder import RosTopic
from rtloop.errors import PortValueError
from rtloop.ipc.ports import RunningApp, app_from_registry, connect_app, port_range
from rtloop.ipc.status import CONTROL_WORDS, ControlWord, WordBlock
from rtloop.ros.dds import RosPublisher, RosSubscriber
from rtloop.ros.messages import Float64, float64_multi_array, joint_state
from rtloop.ros.types import ROS_TYPES
from rtloop.ros.validate import MessageValidator, RateLimitedWarner

POLL_INTERVAL_S = 0.002
STATS_INTERVAL_S = 1.0


def values_of(message: Any) -> Any:
    """The numbers a message carries: ``data`` (Float64, Float64MultiArray) or ``position``."""
    if hasattr(message, "position"):
        return message.position
    data = message.data
    return [data] if isinstance(data, float | int) and not isinstance(data, bool) else data


def message_for(msg_type: str, values: list[float], stamp_ns: int, joint_names: tuple[str, ...]) -> Any:
    if msg_type == "sensor_msgs/msg/JointState":
        names = joint_names or tuple(f"joint{i}" for i in range(len(values)))
        return joint_state(names, values, stamp_ns)
    if msg_type == "std_msgs/msg/Float64":
        return Float64(data=float(values[0]))
    return float64_multi_array(values)


class _Stop:
    """Set by SIGTERM/SIGINT, or when the app's supervisor is gone."""

    def __init__(self, app: RunningApp) -> None:
        self.requested = False
        self.app = app
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, self._request)

    def _request(self, _signum: int, _frame: object) -> None:
        self.requested = True

    def __bool__(self) -> bool:
        return self.requested or not self.app.alive()


class _Stats:
    def __init__(self, topic: RosTopic, pipe: Any) -> None:
        self.topic, self.pipe = topic, pipe
        self.messages = 0
        self.rejected: dict[str, Any] = {}
        self.last_sent = 0.0

    def send(self, force: bool = False) -> None:
        now = time.monotonic()
        if self.pipe is None or (not force and now - self.last_sent < STATS_INTERVAL_S):
            return
        self.last_sent = now
        try:
            self.pipe.send({"kind": "stats", "messages": self.messages, **self.rejected})
        except (BrokenPipeError, OSError):
            self.pipe = None


def _wall_offset_ns(app: RunningApp, stop: Any) -> tuple[int, int] | None:
    """(T0 on CLOCK_MONOTONIC, wall clock − monotonic clock), to stamp ticks with wall time.

    Waits for the app to pick T0; None if the bridge is stopped (or the app dies) first.
    """
    control = WordBlock(app.segment(app.registry["control"]), 0, CONTROL_WORDS)
    while not control[ControlWord.T0_NS]:
        if stop:
            return None
        time.sleep(0.01)
    return control[ControlWord.T0_NS], time.time_ns() - time.monotonic_ns()


def run_listener(app: RunningApp, topic: RosTopic, stop: Any, stats: _Stats) -> None:
    """Publish what an output port sends, until stopped."""
    info = app.ports[topic.port]
    publisher = RosPublisher(topic.topic, topic.msg_type, qos=topic.qos, domain_id=topic.domain_id)
    epoch = _wall_offset_ns(app, stop)
    if epoch is None:
        publisher.close()
        return
    t0_ns, wall_offset_ns = epoch
    period_ns = int(info["period_ns"])
    with app.reader(topic.port) as reader, publisher:
        while not stop:
            ticks, rows = reader.read()
            for tick, row in zip(ticks.tolist(), rows.tolist(), strict=True):
                if tick % topic.every:
                    continue
                stamp_ns = t0_ns + tick * period_ns + wall_offset_ns
                publisher.publish(message_for(topic.msg_type, row, stamp_ns, topic.joint_names))
                stats.messages += 1
            stats.send()
            if not len(ticks):
                time.sleep(POLL_INTERVAL_S)


def run_talker(app: RunningApp, topic: RosTopic, stop: Any, stats: _Stats) -> None:
    """Write what arrives on a topic to an input port, checking every message first."""
    info = app.ports[topic.port]
    warner = RateLimitedWarner(1.0, emit=lambda text: print(f"rtloop bridge {topic.topic}: {text}",
                                                             file=sys.stderr, flush=True))
    validator = MessageValidator(int(info["size"]), allow_nonfinite=bool(info["allow_nonfinite"]),
                                 what=f"{topic.topic} → port {topic.port}", warner=warner,
                                 value_range=narrowest_range(topic.value_range, port_range(info)))
    refused = 0
    with RosSubscriber(topic.topic, topic.msg_type, qos=topic.qos, domain_id=topic.domain_id) as subscriber:
        while not stop:
            for message in subscriber.take():
                values = validator.check(values_of(message))
                if values is None:
                    continue
                try:
                    app.write(topic.port, values)
                    stats.messages += 1
                except PortValueError as error:  # e.g. the port is fed from a profile in this run
                    refused += 1
                    warner.warn(str(error), key="port")
            stats.rejected = {**validator.counts.to_json(), "refused_by_port": refused}
            stats.send()
            subscriber.wait(0.05)


def narrowest_range(*ranges: tuple[float, float] | None) -> tuple[float, float] | None:
    """Where all the given ranges overlap (the topic's and the port's); None if none is given."""
    given = [r for r in ranges if r is not None]
    if not given:
        return None
    return max(low for low, _ in given), min(high for _, high in given)


def bridge_process_main(topic: RosTopic, registry_path: str, pipe: Any = None) -> None:
    """Entry point of a bridge process started by the supervisor."""
    from rtloop import rt

    rt.die_with_parent(signal.SIGTERM)
    app = app_from_registry(Path(registry_path), owner_uid=os.geteuid())
    if os.getppid() != app.pid:  # the supervisor died before we could ask to follow it
        return
    stats = _Stats(topic, pipe)
    try:
        run_bridge(app, topic, stats)
    except Exception as error:
        if pipe is not None:
            pipe.send({"kind": "error", "reason": f"{type(error).__name__}: {error}"})
        raise SystemExit(1) from None
    finally:
        stats.send(force=True)


def run_bridge(app: RunningApp, topic: RosTopic, stats: _Stats) -> None:
    stop = _Stop(app)
    if topic.direction == "publish":
        run_listener(app, topic, stop, stats)
    else:
        run_talker(app, topic, stop, stats)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rtloop bridge", description=__doc__.splitlines()[0])
    kinds = parser.add_subparsers(dest="kind", required=True)
    listener = kinds.add_parser("listener", help="publish an output port on a ROS 2 topic")
    talker = kinds.add_parser("talker", help="feed an input port from a ROS 2 topic")
    for sub, default_qos in ((listener, "sensor"), (talker, "reliable")):
        sub.add_argument("--app", required=True, help="name of the running app")
        sub.add_argument("--port", required=True)
        sub.add_argument("--topic", required=True, help="ROS 2 topic, e.g. /jiwy/angles")
        sub.add_argument("--type", default="std_msgs/msg/Float64MultiArray", choices=ROS_TYPES)
        sub.add_argument("--qos", default=default_qos, choices=("sensor", "reliable"))
        sub.add_argument("--domain-id", type=int, default=None, help="default: ROS_DOMAIN_ID or 0")
    listener.add_argument("--joint-names", nargs="+", default=[], help="for JointState: one name per value")
    listener.add_argument("--every", type=int, default=1, help="publish every N-th tick")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    app = connect_app(args.app, timeout_s=10)
    direction = "publish" if args.kind == "listener" else "subscribe"
    topic = RosTopic(direction, args.topic, args.port, args.type, args.qos,
                     tuple(getattr(args, "joint_names", ())), getattr(args, "every", 1), args.domain_id)
    stats = _Stats(topic, None)
    print(f"rtloop bridge {args.kind}: {args.topic} {'←' if direction == 'publish' else '→'} "
          f"{app.name}.{args.port}; Ctrl-C to stop", file=sys.stderr)
    run_bridge(app, topic, stats)
    print(f"rtloop bridge {args.kind}: {stats.messages} messages", file=sys.stderr)
    return 0
