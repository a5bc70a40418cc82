"""The rclpy backend of :class:`~rtloop.ros.RosPublisher` and ``RosSubscriber``.

Used where a ROS 2 install is sourced (e.g. a Raspberry Pi, which has no cyclonedds
wheel). Messages given to ``publish`` may be rtloop message objects (converted by
field name) or rclpy messages; ``take`` returns rclpy messages, whose fields have the
same names (``msg.position``, ``msg.header.stamp.sec``), so calling code is the same.

Not exercised by the test suite where rclpy is absent; the import guard is.
"""

from __future__ import annotations

import dataclasses
import importlib
import threading
from collections import deque
from typing import Any

from rtloop.ros.errors import RosConfigError, require_rclpy

_nodes: dict[int, tuple[Any, Any, Any]] = {}
_nodes_lock = threading.Lock()


def ros_message_class(msg_type: Any) -> Any:
    """Return the rclpy class for an rtloop message class, a ROS 2 name, or an rclpy class."""
    if isinstance(msg_type, str):
        name = msg_type
    elif hasattr(msg_type, "__idl_typename__"):
        from rtloop.ros.messages import ros_type_name

        name = ros_type_name(msg_type)
    else:
        return msg_type  # already an rclpy message class
    package, _msg, type_name = name.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), type_name)
    except (ImportError, AttributeError):
        raise RosConfigError(f"ROS 2 message type {name!r} is not installed") from None


def _node(domain_id: int) -> tuple[Any, Any, Any]:
    # One context, node and executor per domain, like one DDS participant per domain.
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    with _nodes_lock:
        if domain_id not in _nodes:
            context = rclpy.Context()
            rclpy.init(context=context, domain_id=domain_id)
            node = rclpy.create_node(f"rtloop_bridge_{domain_id}", context=context)
            executor = SingleThreadedExecutor(context=context)
            executor.add_node(node)
            _nodes[domain_id] = (context, node, executor)
        return _nodes[domain_id]


def _profile(qos: str, depth: int) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    reliability = ReliabilityPolicy.BEST_EFFORT if qos == "sensor" else ReliabilityPolicy.RELIABLE
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=reliability, durability=DurabilityPolicy.VOLATILE)


def _to_ros(msg: Any, ros_class: Any) -> Any:
    if isinstance(msg, ros_class):
        return msg
    from rosidl_runtime_py.set_message import set_message_fields

    ros_msg = ros_class()
    set_message_fields(ros_msg, dataclasses.asdict(msg))
    return ros_msg


class RclpyPublisher:
    """rclpy publisher behind :class:`~rtloop.ros.RosPublisher`."""

    def __init__(self, topic: str, msg_type: Any, qos: str, depth: int,
                 domain_id: int) -> None:
        require_rclpy()
        self.msg_type = msg_type
        self._ros_class = ros_message_class(msg_type)
        _context, self._node, _executor = _node(domain_id)
        self._pub = self._node.create_publisher(self._ros_class, topic, _profile(qos, depth))

    def publish(self, msg: Any) -> None:
        self._pub.publish(_to_ros(msg, self._ros_class))

    def subscriber_count(self) -> int:
        return int(self._pub.get_subscription_count())

    def close(self) -> None:
        if self._pub is not None:
            self._node.destroy_publisher(self._pub)
            self._pub = None


class RclpySubscriber:
    """rclpy subscription behind :class:`~rtloop.ros.RosSubscriber`."""

    def __init__(self, topic: str, msg_type: Any, qos: str, depth: int,
                 domain_id: int) -> None:
        require_rclpy()
        self.msg_type = msg_type
        self._ros_class = ros_message_class(msg_type)
        _context, self._node, self._executor = _node(domain_id)
        self._queue: deque[Any] = deque(maxlen=depth)
        self._sub = self._node.create_subscription(
            self._ros_class, topic, self._queue.append, _profile(qos, depth))

    def take(self, max_messages: int) -> list[Any]:
        # Run callbacks that are ready without waiting; each appends one message.
        for _ in range(max_messages):
            before = len(self._queue)
            self._executor.spin_once(timeout_sec=0)
            if len(self._queue) == before:
                break
        count = min(max_messages, len(self._queue))
        return [self._queue.popleft() for _ in range(count)]

    def wait(self, timeout_s: float) -> bool:
        if not self._queue:
            self._executor.spin_once(timeout_sec=timeout_s)
        return bool(self._queue)

    def publisher_count(self) -> int:
        return int(self._sub.get_publisher_count() if hasattr(self._sub, "get_publisher_count")
                   else self._node.count_publishers(self._sub.topic_name))

    def close(self) -> None:
        if self._sub is not None:
            self._node.destroy_subscription(self._sub)
            self._sub = None
