"""ROS 2 bridge nodes: the thesis's listener (RT data → topic) and talker (topic → RT).

Each bridge is a non-real-time process attached to a running app's port:

    rtloop bridge listener --app jiwy --port angles --topic /jiwy/angles --type sensor_msgs/msg/JointState \\
        --joint-names pan tilt
    rtloop bridge talker --app jiwy --topic /jiwy/setpoint --port setpoint

A listener publishes every tick an output port sends (or every N-th, ``--every``). It
knows the task's timeline (T0 and the period P, from the app's control block and
registry) and sleeps until just after tick k should have been sent, T0 + k·P + lag, where
lag is learnt from when ticks did arrive; it never polls on a clock of its own.
a talker checks every message (type, length, NaN/inf) before it reaches the port —
rejected ones are counted and warned about at most once a second. A bridge never
stalls the real-time side: ports drop and count when nobody reads them.
"""

from __future__ import annotations

import functools
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from rtloop.app.specs import RosTopic
from rtloop.errors import PortValueError
from rtloop.ipc.ports import RunningApp, app_from_registry, port_range
from rtloop.ipc.status import CONTROL_WORDS, ControlWord, WordBlock
from rtloop.ros.cdr import encoder_for
from rtloop.ros.dds import RosPublisher, RosSubscriber
from rtloop.ros.messages import Float64, float64_multi_array, joint_state
from rtloop.ros.validate import MessageValidator, RateLimitedWarner

STATS_INTERVAL_S = 1.0
ALIVE_CHECK_INTERVAL_S = 0.2
# A tick not yet sent at the expected time is looked for again this much later.
RETRY_NS = 25_000
TIMER_SLACK_NS = 1_000


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
        self.checked_at, self.app_alive = 0.0, True
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, self._request)

    def _request(self, _signum: int, _frame: object) -> None:
        self.requested = True

    def __bool__(self) -> bool:
        if self.requested:
            return True
        now = time.monotonic()
        if now - self.checked_at >= ALIVE_CHECK_INTERVAL_S:  # the listener asks every tick: keep it cheap
            self.checked_at, self.app_alive = now, self.app.alive()
        return not self.app_alive


class BridgeStats:
    def __init__(self, topic: RosTopic, pipe: Any) -> None:
        self.topic, self.pipe = topic, pipe
        self.messages = 0
        self.rejected: dict[str, Any] = {}
        self.last_sent = 0.0

    def ready(self) -> None:
        """Its DDS entity exists: the supervisor may pick T0 (runtime/bridges.py)."""
        try:
            if self.pipe is not None:
                self.pipe.send({"kind": "ready"})
        except (BrokenPipeError, OSError):
            self.pipe = None

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


class TickTimeline:
    """When the listener looks for tick k: T0 + k·P + lag, lag learnt from when ticks arrive.

    A task sends tick k once it has stepped, a little after its release T0 + k·P. Found at
    the first look, the tick may have been waiting: the lag shrinks by an eighth. Found
    only after looking again, it becomes the time it took. So the listener wakes about
    when the tick is sent, without spinning and without a poll interval of its own.
    """

    def __init__(self, t0_ns: int, period_ns: int, every: int = 1) -> None:
        self.t0_ns, self.period_ns, self.every = t0_ns, period_ns, every
        self.lag_ns = 0

    def release_ns(self, tick: int) -> int:
        return self.t0_ns + tick * self.period_ns

    def next_tick(self, after_tick: int) -> int:
        """The first tick after ``after_tick`` that is published (a multiple of ``every``)."""
        return (after_tick // self.every + 1) * self.every

    def look_at_ns(self, tick: int) -> int:
        return self.release_ns(tick) + self.lag_ns

    def found(self, tick: int, found_ns: int, looked_again: bool) -> None:
        if looked_again:
            self.lag_ns = min(max(0, found_ns - self.release_ns(tick)), self.period_ns * self.every)
        else:
            self.lag_ns -= self.lag_ns >> 3


def _sender(publisher: RosPublisher, topic: RosTopic, size: int) -> Any:
    """``send(values, stamp_ns)``: CDR encoded here if it gives the DDS library's own bytes, else generic."""
    def generic(values: list[float], stamp_ns: int) -> None:
        publisher.publish(message_for(topic.msg_type, values, stamp_ns, topic.joint_names))

    if not publisher.takes_cdr:
        return generic
    encode = encoder_for(topic.msg_type, topic.joint_names)
    probe_values, probe_stamp_ns = [0.1 * (i + 1) for i in range(size)], 1_700_000_000_123_456_789
    reference = message_for(topic.msg_type, probe_values, probe_stamp_ns, topic.joint_names).serialize()
    if encode(probe_values, probe_stamp_ns) != reference.ljust(-(-len(reference) // 4) * 4, b"\0"):
        return generic  # another data representation (XCDR2): let the DDS library encode

    def fast(values: list[float], stamp_ns: int) -> None:
        publisher.publish_cdr(encode(values, stamp_ns))

    return fast


def run_listener(app: RunningApp, topic: RosTopic, stop: Any, stats: BridgeStats) -> None:
    """Publish what an output port sends, until stopped, waking on the task's timeline."""
    from rtloop.linux import rt

    info = app.ports[topic.port]
    publisher = RosPublisher(topic.topic, topic.msg_type, qos=topic.qos, domain_id=topic.domain_id)
    stats.ready()
    epoch = _wall_offset_ns(app, stop)
    if epoch is None:
        publisher.close()
        return
    t0_ns, wall_offset_ns = epoch
    period_ns = int(info["period_ns"])
    timeline = TickTimeline(t0_ns, period_ns, topic.every)
    sleeper = rt.AbsoluteSleeper()
    try:
        rt.set_timer_slack(TIMER_SLACK_NS)
    except OSError:
        pass  # only later wake-ups
    send = _sender(publisher, topic, int(info["size"]))
    wanted = 0
    with app.reader(topic.port) as reader, publisher:
        while not stop:
            sleeper.sleep_until(timeline.look_at_ns(wanted))
            ticks, rows = reader.read()
            looked_again = False
            give_up_ns = timeline.release_ns(timeline.next_tick(wanted))
            while not len(ticks) and rt.now_ns() + RETRY_NS < give_up_ns and not stop:
                sleeper.sleep_until(rt.now_ns() + RETRY_NS)
                ticks, rows = reader.read()
                looked_again = True
            if not len(ticks):  # not sent this period (a skipped release, or the run is ending)
                wanted = timeline.next_tick(wanted)
                continue
            tick_list = ticks.tolist()
            if wanted in tick_list:
                timeline.found(wanted, rt.now_ns(), looked_again)
            for tick, row in zip(tick_list, rows.tolist(), strict=True):
                if tick % topic.every:
                    continue
                send(row, t0_ns + tick * period_ns + wall_offset_ns)
                stats.messages += 1
            wanted = timeline.next_tick(tick_list[-1])
            stats.send()


def run_talker(app: RunningApp, topic: RosTopic, stop: Any, stats: BridgeStats) -> None:
    """Write what arrives on a topic to an input port, checking every message first."""
    info = app.ports[topic.port]
    warner = RateLimitedWarner(1.0, emit=lambda text: print(f"rtloop bridge {topic.topic}: {text}",
                                                             file=sys.stderr, flush=True))
    validator = MessageValidator(int(info["size"]), allow_nonfinite=bool(info["allow_nonfinite"]),
                                 what=f"{topic.topic} → port {topic.port}", warner=warner,
                                 value_range=narrowest_range(topic.value_range, port_range(info)))
    refused = 0
    with app.writer(topic.port) as writer, \
            RosSubscriber(topic.topic, topic.msg_type, qos=topic.qos, domain_id=topic.domain_id) as subscriber:
        stats.ready()
        while not stop:
            for message in subscriber.take():
                values = validator.check(values_of(message))
                if values is None:
                    continue
                try:
                    writer.write(values)
                    stats.messages += 1
                except PortValueError as error:  # e.g. the port is fed from a profile in this run
                    refused += 1
                    warner.warn(str(error), key="port")
            stats.rejected = {**validator.counts.to_json(), "refused_by_port": refused}
            stats.send()
            subscriber.wait(0.05)


def narrowest_range(*ranges: tuple[Any, Any] | None) -> tuple[Any, Any] | None:
    """Where all the given ranges overlap (the topic's and the port's, value by value when either
    has one bound per value); None if none is given."""
    given = [r for r in ranges if r is not None]
    if not given:
        return None
    low = functools.reduce(np.maximum, (np.asarray(r[0], dtype=np.float64) for r in given))
    high = functools.reduce(np.minimum, (np.asarray(r[1], dtype=np.float64) for r in given))
    return _plain(low), _plain(high)


def _plain(bound: np.ndarray) -> float | tuple[float, ...]:
    return float(bound) if bound.ndim == 0 else tuple(float(v) for v in bound)


def bridge_process_main(topic: RosTopic, registry_path: str, pipe: Any = None) -> None:
    """Entry point of a bridge process started by the supervisor."""
    from rtloop.linux import rt

    rt.die_with_parent(signal.SIGTERM)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # a closing terminal: the supervisor stops the bridges in order
    app = app_from_registry(Path(registry_path), owner_uid=os.geteuid())
    if os.getppid() != app.pid:  # the supervisor died before we could ask to follow it
        return
    stats = BridgeStats(topic, pipe)
    try:
        run_bridge(app, topic, stats)
    except Exception as error:
        if pipe is not None:
            pipe.send({"kind": "error", "reason": f"{type(error).__name__}: {error}"})
        raise SystemExit(1) from None
    finally:
        stats.send(force=True)


def run_bridge(app: RunningApp, topic: RosTopic, stats: BridgeStats) -> None:
    stop = _Stop(app)
    if topic.direction == "publish":
        run_listener(app, topic, stop, stats)
    else:
        run_talker(app, topic, stop, stats)
