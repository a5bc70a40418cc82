"""Publish and subscribe to ROS 2 topics over DDS, with or without a ROS 2 install.

``RosPublisher`` and ``RosSubscriber`` speak ROS 2 conventions: the DDS topic of
ROS 2 topic ``/jiwy/angles`` is ``rt/jiwy/angles``, the domain is ``ROS_DOMAIN_ID``
(default 0) and the QoS presets match rclpy's default profile (the default here too)
and its ``qos_profile_sensor_data``. The default backend is the ``cyclonedds`` Python package (no ROS 2
needed); ``backend="rclpy"`` uses a sourced ROS 2 install instead, with the same API.

These run in non-real-time processes only (bridges, tools, tests): DDS allocates,
locks and does I/O.
"""

from __future__ import annotations

import re
import threading
import time
from typing import Any

from rtloop.ros.errors import RosConfigError, choose_backend, domain_id_from_env

QOS_PRESETS = ("reliable", "sensor")
"""``reliable`` (the default): reliable, keep last 10, volatile — ROS 2's default profile.
A reliable writer matches reliable readers (rclpy's default, ``ros2 topic echo``) and
best-effort ones alike; keep-last means a slow reader never blocks the writer for long.
``sensor``: best effort, keep last 5, volatile (rclpy ``qos_profile_sensor_data``); a
best-effort writer matches best-effort readers only."""
DEFAULT_QOS = "reliable"

_HISTORY_DEPTH = {"sensor": 5, "reliable": 10}
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def dds_topic_name(topic: str) -> str:
    """Return the DDS topic name of ROS 2 topic ``topic``: ``/a/b`` → ``rt/a/b``.

    A name without a leading slash is taken relative to the root namespace, as for a
    node without a namespace.

    Raises:
        RosConfigError: ``topic`` is not a valid ROS 2 topic name (tokens of letters,
            digits and underscores, not starting with a digit, separated by ``/``).
    """
    tokens = topic.removeprefix("/").split("/")
    if not all(_TOKEN.fullmatch(token) for token in tokens) or "__" in topic:
        raise RosConfigError(
            f"invalid ROS 2 topic name {topic!r}: expected tokens of letters, digits and "
            "single underscores, not starting with a digit, separated by '/'"
        )
    return "rt/" + "/".join(tokens)


def _check_depth(qos: str, depth: int | None) -> int:
    if depth is None:
        return _HISTORY_DEPTH[qos]
    if not isinstance(depth, int) or depth < 1:
        raise RosConfigError(f"history depth must be a positive integer, got {depth!r}")
    return depth


def _check_qos(qos: str) -> str:
    if qos not in QOS_PRESETS:
        raise RosConfigError(f"unknown QoS preset {qos!r}: expected one of {QOS_PRESETS}")
    return qos


class _Endpoint:
    """What a publisher and a subscriber share: checked settings, a backend, closing."""

    def __init__(
        self,
        topic: str,
        msg_type: Any,
        qos: str = DEFAULT_QOS,
        domain_id: int | None = None,
        backend: str = "auto",
        depth: int | None = None,
    ) -> None:
        self.topic = topic
        self.dds_topic = dds_topic_name(topic)
        self.qos = _check_qos(qos)
        self.depth = _check_depth(qos, depth)
        self.domain_id = domain_id_from_env(domain_id)
        self.backend = choose_backend(backend)
        self._impl: Any = self._open(msg_type)
        self.msg_type = self._impl.msg_type

    def _open(self, msg_type: Any) -> Any:
        raise NotImplementedError

    def close(self) -> None:
        """Delete the DDS writer or reader. Safe to call twice."""
        self._impl.close()

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RosPublisher(_Endpoint):
    """Publishes messages of one type on one ROS 2 topic.

    Args:
        topic: ROS 2 topic name, e.g. ``"/jiwy/angles"``.
        msg_type: a message class from :mod:`rtloop.ros.messages`, or its ROS 2 name
            such as ``"sensor_msgs/msg/JointState"``.
        qos: ``"reliable"`` (default) or ``"sensor"`` (best effort); see :data:`QOS_PRESETS`.
        domain_id: DDS domain; ``None`` reads ``ROS_DOMAIN_ID`` (default 0).
        backend: ``"auto"`` (cyclonedds, else rclpy), ``"cyclonedds"`` or ``"rclpy"``.
        depth: history depth instead of the preset's (5 or 10); a subscriber that may
            stall longer than ``depth`` message periods loses messages.

    Raises:
        RosUnavailable: the backend cannot be imported (the message says how to fix it).
        RosConfigError: invalid topic, QoS preset, domain id or message type.
    """

    published = 0
    """Messages handed to DDS so far."""

    def _open(self, msg_type: Any) -> Any:
        if self.backend == "cyclonedds":
            return _CyclonePublisher(self.dds_topic, msg_type, self.qos, self.depth, self.domain_id)
        from rtloop.ros.rclpy_backend import RclpyPublisher

        return RclpyPublisher(self.topic, msg_type, self.qos, self.depth, self.domain_id)

    def publish(self, msg: Any) -> None:
        """Send ``msg`` (an instance of ``msg_type``). Does not wait for subscribers."""
        self._impl.publish(msg)
        self.published += 1

    def publish_cdr(self, data: bytes) -> None:
        """Send a message already encoded (:mod:`rtloop.ros.cdr`): the listener's fast path.

        Raises:
            RosConfigError: this backend cannot send encoded bytes (check :attr:`takes_cdr`).
        """
        if not self.takes_cdr:
            raise RosConfigError(f"the {self.backend} backend does not send pre-encoded messages")
        self._impl.publish_cdr(data)
        self.published += 1

    @property
    def takes_cdr(self) -> bool:
        """Whether :meth:`publish_cdr` works here (the cyclonedds backend)."""
        return hasattr(self._impl, "publish_cdr")

    def subscriber_count(self) -> int:
        """Return how many subscriptions currently match this publisher."""
        return int(self._impl.subscriber_count())

    def wait_for_subscribers(self, count: int = 1, timeout_s: float = 5.0) -> bool:
        """Wait until at least ``count`` subscriptions match; return whether they did."""
        return _poll(lambda: self.subscriber_count() >= count, timeout_s)


class RosSubscriber(_Endpoint):
    """Receives messages of one type from one ROS 2 topic; polled with :meth:`take`.

    Arguments are those of :class:`RosPublisher`. Incoming messages queue up to the
    history depth (5 for ``"sensor"``, 10 for ``"reliable"``, or ``depth``); older unread ones
    are dropped by DDS, so poll at least as often as that many messages arrive.
    """

    def _open(self, msg_type: Any) -> Any:
        if self.backend == "cyclonedds":
            return _CycloneSubscriber(self.dds_topic, msg_type, self.qos, self.depth, self.domain_id)
        from rtloop.ros.rclpy_backend import RclpySubscriber

        return RclpySubscriber(self.topic, msg_type, self.qos, self.depth, self.domain_id)

    def take(self, max_messages: int = 64) -> list[Any]:
        """Return the messages received since the last call, oldest first. Never blocks."""
        return list(self._impl.take(max_messages))

    def wait(self, timeout_s: float) -> bool:
        """Block up to ``timeout_s`` until a message is available; return whether one is."""
        return bool(self._impl.wait(timeout_s))

    def publisher_count(self) -> int:
        """Return how many publications currently match this subscriber."""
        return int(self._impl.publisher_count())

    def wait_for_publishers(self, count: int = 1, timeout_s: float = 5.0) -> bool:
        """Wait until at least ``count`` publications match; return whether they did."""
        return _poll(lambda: self.publisher_count() >= count, timeout_s)


def _poll(condition: Any, timeout_s: float, interval_s: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() >= deadline:
            return False
        time.sleep(interval_s)
    return True


# --- cyclonedds backend -------------------------------------------------------------

_participants: dict[int, Any] = {}
_domains: dict[int, Any] = {}
_participants_lock = threading.Lock()


def _participant(domain_id: int) -> Any:
    # One participant per domain and process: each costs threads, sockets and discovery.
    from cyclonedds.domain import Domain, DomainParticipant

    from rtloop.ros.discovery import cyclone_config_string

    with _participants_lock:
        if domain_id not in _participants:
            config = cyclone_config_string()  # ROS_AUTOMATIC_DISCOVERY_RANGE & co., then CYCLONEDDS_URI
            if config is not None:
                _domains[domain_id] = Domain(domain_id, config)  # kept: the participant lives in it
            _participants[domain_id] = DomainParticipant(domain_id)
        return _participants[domain_id]


def _resolve_idl_type(msg_type: Any) -> Any:
    from cyclonedds.idl import IdlStruct

    from rtloop.ros.messages import ROS_TYPES

    if isinstance(msg_type, str):
        if msg_type not in ROS_TYPES:
            raise RosConfigError(
                f"unknown ROS 2 message type {msg_type!r}: expected one of {sorted(ROS_TYPES)}"
                " or an IdlStruct class"
            )
        return ROS_TYPES[msg_type]
    if isinstance(msg_type, type) and issubclass(msg_type, IdlStruct):
        return msg_type
    raise RosConfigError(f"message type {msg_type!r} is neither a ROS 2 type name nor an "
                         "IdlStruct class")


def _cyclone_qos(qos: str, depth: int) -> Any:
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.util import duration

    if qos == "sensor":
        reliability = Policy.Reliability.BestEffort
    else:
        reliability = Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100))
    return Qos(
        reliability,
        Policy.History.KeepLast(depth),
        Policy.Durability.Volatile,
    )


class _CyclonePublisher:
    def __init__(self, dds_topic: str, msg_type: Any, qos: str, depth: int,
                 domain_id: int) -> None:
        from cyclonedds.pub import DataWriter
        from cyclonedds.topic import Topic

        self.msg_type = _resolve_idl_type(msg_type)
        participant = _participant(domain_id)
        self._topic = Topic(participant, dds_topic, self.msg_type)
        self._writer = DataWriter(participant, self._topic, qos=_cyclone_qos(qos, depth))

    def publish(self, msg: Any) -> None:
        self._writer.write(msg)

    def publish_cdr(self, data: bytes) -> None:
        # What DataWriter.write does after serialising: hand the CDR bytes to the C layer.
        from cyclonedds._clayer import ddspy_write

        if ddspy_write(self._writer._ref, data) < 0:
            from cyclonedds.core import DDSException

            raise DDSException(-1, f"Occurred while writing a sample on {self._topic.name}")

    def subscriber_count(self) -> int:
        return len(self._writer.get_matched_subscriptions())

    def close(self) -> None:
        self._writer.__del__()
        self._topic.__del__()


class _CycloneSubscriber:
    def __init__(self, dds_topic: str, msg_type: Any, qos: str, depth: int,
                 domain_id: int) -> None:
        from cyclonedds.core import ReadCondition, SampleState, WaitSet
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic

        self.msg_type = _resolve_idl_type(msg_type)
        participant = _participant(domain_id)
        self._topic = Topic(participant, dds_topic, self.msg_type)
        self._reader = DataReader(participant, self._topic, qos=_cyclone_qos(qos, depth))
        self._condition = ReadCondition(self._reader, SampleState.NotRead)
        self._waitset = WaitSet(participant)
        self._waitset.attach(self._condition)

    def take(self, max_messages: int) -> list[Any]:
        from cyclonedds.internal import InvalidSample

        samples = self._reader.take(N=max_messages)
        # Invalid samples carry only instance state changes (a writer went away).
        return [s for s in samples if not isinstance(s, InvalidSample)]

    def wait(self, timeout_s: float) -> bool:
        return self._waitset.wait(max(0, int(timeout_s * 1e9))) > 0

    def publisher_count(self) -> int:
        return len(self._reader.get_matched_publications())

    def close(self) -> None:
        self._waitset.__del__()
        self._condition.__del__()
        self._reader.__del__()
        self._topic.__del__()
