"""ROS 2 message types: names, helpers, and the exact CDR bytes a ROS 2 node sends."""

from __future__ import annotations

import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from rtloop.ros import messages as m


def test_dds_and_ros_type_names():
    assert m.dds_type_name(m.JointState) == "sensor_msgs::msg::dds_::JointState_"
    assert m.dds_type_name(m.Header) == "std_msgs::msg::dds_::Header_"
    assert m.dds_type_name(m.Time) == "builtin_interfaces::msg::dds_::Time_"
    assert m.dds_type_name(m.Float64) == "std_msgs::msg::dds_::Float64_"
    for ros_name, cls in m.ROS_TYPES.items():
        assert m.ros_type_name(cls) == ros_name


def test_time_split_keeps_nanosec_in_range():
    assert m.time_from_ns(1_500_000_000) == m.Time(sec=1, nanosec=500_000_000)
    assert m.time_from_ns(-1) == m.Time(sec=-1, nanosec=999_999_999)
    for ns in (0, 1, -1, 123_456_789_012, -5_000_000_001):
        assert m.time_to_ns(m.time_from_ns(ns)) == ns


def test_helpers_accept_numpy_and_check_lengths():
    msg = m.float64_multi_array(np.array([1.5, 2.5]), label="u")
    assert msg.data == [1.5, 2.5] and all(type(v) is float for v in msg.data)
    assert msg.layout.dim[0] == m.MultiArrayDimension(label="u", size=2, stride=2)
    assert m.float64_multi_array([1]).layout.dim == []
    js = m.joint_state(("pan", "tilt"), np.array([0.5, -0.5]), 3_000_000_007)
    assert js.name == ["pan", "tilt"] and js.position == [0.5, -0.5]
    assert js.header.stamp == m.Time(sec=3, nanosec=7)
    with pytest.raises(ValueError, match="2 names but 1 positions"):
        m.joint_state(["a", "b"], [1.0], 0)


def _cdr_string(text: str, offset: int) -> tuple[bytes, int]:
    raw = text.encode() + b"\0"
    return struct.pack("<I", len(raw)) + raw, offset + 4 + len(raw)


def _pad(buf: bytes, align: int) -> bytes:
    return buf + b"\0" * (-len(buf) % align)


def test_float64_multi_array_bytes_are_ros2_cdr():
    """Hand-encoded XCDR1 little endian, as rmw_cyclonedds and Fast DDS write it."""
    pytest.importorskip("cyclonedds")
    body = struct.pack("<I", 1)  # one dimension
    label, _ = _cdr_string("u", 0)
    body += label
    body = _pad(body, 4) + struct.pack("<II", 2, 2)  # size, stride
    body += struct.pack("<I", 0)  # data_offset
    body += struct.pack("<I", 2)  # two doubles, aligned to 8 from the body start
    body = _pad(body, 8) + struct.pack("<2d", 1.0, -2.5)
    expected = b"\x00\x01\x00\x00" + body  # encapsulation: CDR_LE, options 0
    assert m.float64_multi_array([1.0, -2.5], label="u").serialize() == expected


def test_joint_state_bytes_are_ros2_cdr():
    pytest.importorskip("cyclonedds")
    body = struct.pack("<iI", -3, 7)
    frame, _ = _cdr_string("base", 0)
    body += frame
    body = _pad(body, 4) + struct.pack("<I", 1)
    name, _ = _cdr_string("pan", 0)
    body += name
    body = _pad(body, 4) + struct.pack("<I", 1)
    body = _pad(body, 8) + struct.pack("<d", 0.25)
    body += struct.pack("<I", 0) + struct.pack("<I", 0)  # velocity, effort: empty
    stamp_ns = -3 * 1_000_000_000 + 7
    msg = m.joint_state(["pan"], [0.25], stamp_ns, frame_id="base")
    assert msg.serialize() == b"\x00\x01\x00\x00" + body
    assert m.JointState.deserialize(msg.serialize()) == msg


def test_messages_work_as_plain_dataclasses_without_cyclonedds():
    code = textwrap.dedent(
        """
        import sys
        sys.modules["cyclonedds"] = None  # as on aarch64, where there is no wheel
        sys.modules["rclpy"] = None  # and no ROS 2 sourced
        from rtloop.ros import messages
        from rtloop.ros.dds import RosPublisher
        from rtloop.ros.errors import RosUnavailable
        from rtloop.ros.messages import joint_state
        assert not messages.HAVE_CYCLONEDDS
        msg = joint_state(["a"], [1.0], 5)
        assert msg.position == [1.0] and msg.header.stamp.nanosec == 5
        assert messages.ros_type_name(messages.JointState) == "sensor_msgs/msg/JointState"
        for backend in ("auto", "cyclonedds", "rclpy"):
            try:
                RosPublisher("/x", messages.JointState, backend=backend, domain_id=1)
            except RosUnavailable as exc:
                print(backend, "|", exc)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=30, check=True).stdout
    lines = dict(line.split(" | ") for line in out.strip().splitlines())
    assert "pip install 'rtloop[ros]'" in lines["auto"]
    assert "aarch64" in lines["cyclonedds"]
    assert "rclpy" in lines["rclpy"] and "source /opt/ros" in lines["rclpy"]
