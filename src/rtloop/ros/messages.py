"""ROS 2 message types declared for DDS, without a ROS 2 install.

A ROS 2 node on Cyclone DDS or Fast DDS finds a topic by its mangled name
(``rt/<topic>``) and its DDS type name, which rosidl spells
``<package>::msg::dds_::<Type>_``. The classes below declare exactly those names and
the ROS 2 field names and types, so their CDR encoding is byte-compatible with what a
ROS 2 node sends and expects. Keep these in the order and with the types of the
``.msg`` files they mirror: the wire format is positional. There is no
``from __future__ import annotations`` here because cyclonedds resolves the field
annotations at run time.

Without ``cyclonedds`` (e.g. on aarch64, where the rclpy backend is used) the same
classes are plain dataclasses: they build and read messages but cannot serialize CDR.
"""

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

try:
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.types import float64, int32, uint32

    if TYPE_CHECKING:  # cyclonedds makes sequence[T] at run time, which mypy cannot read; the field holds a list
        sequence = list
    else:
        from cyclonedds.idl.types import sequence

    HAVE_CYCLONEDDS = True
except ImportError:  # rclpy-only installs: same classes, as plain dataclasses
    from rtloop.ros._plain_idl import IdlStruct, float64, int32, sequence, uint32  # type: ignore[assignment]  # stand-ins

    HAVE_CYCLONEDDS = False

NS_PER_S = 1_000_000_000


@dataclass
class Time(IdlStruct, typename="builtin_interfaces.msg.dds_.Time_"):
    """``builtin_interfaces/msg/Time``: seconds and nanoseconds since an epoch."""

    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs.msg.dds_.Header_"):
    """``std_msgs/msg/Header``: time stamp and coordinate frame of a message."""

    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Float64(IdlStruct, typename="std_msgs.msg.dds_.Float64_"):
    """``std_msgs/msg/Float64``: one double."""

    data: float64 = 0.0


@dataclass
class MultiArrayDimension(IdlStruct, typename="std_msgs.msg.dds_.MultiArrayDimension_"):
    """``std_msgs/msg/MultiArrayDimension``: label, size and stride of one dimension."""

    label: str = ""
    size: uint32 = 0
    stride: uint32 = 0


@dataclass
class MultiArrayLayout(IdlStruct, typename="std_msgs.msg.dds_.MultiArrayLayout_"):
    """``std_msgs/msg/MultiArrayLayout``: dimensions and offset of a multi-array."""

    dim: sequence[MultiArrayDimension] = field(default_factory=list)
    data_offset: uint32 = 0


@dataclass
class Float64MultiArray(IdlStruct, typename="std_msgs.msg.dds_.Float64MultiArray_"):
    """``std_msgs/msg/Float64MultiArray``: a layout and a flat sequence of doubles."""

    layout: MultiArrayLayout = field(default_factory=MultiArrayLayout)
    data: sequence[float64] = field(default_factory=list)


@dataclass
class JointState(IdlStruct, typename="sensor_msgs.msg.dds_.JointState_"):
    """``sensor_msgs/msg/JointState``: named joints with position, velocity and effort.

    As in ROS 2, ``velocity`` and ``effort`` may be empty when not measured.
    """

    header: Header = field(default_factory=Header)
    name: sequence[str] = field(default_factory=list)
    position: sequence[float64] = field(default_factory=list)
    velocity: sequence[float64] = field(default_factory=list)
    effort: sequence[float64] = field(default_factory=list)


ROS_TYPES: dict[str, type[IdlStruct]] = {
    "builtin_interfaces/msg/Time": Time,
    "std_msgs/msg/Header": Header,
    "std_msgs/msg/Float64": Float64,
    "std_msgs/msg/MultiArrayDimension": MultiArrayDimension,
    "std_msgs/msg/MultiArrayLayout": MultiArrayLayout,
    "std_msgs/msg/Float64MultiArray": Float64MultiArray,
    "sensor_msgs/msg/JointState": JointState,
}
"""The message types above by their ROS 2 name (``package/msg/Type``)."""


def dds_type_name(msg_type: type[IdlStruct]) -> str:
    """Return the DDS type name of ``msg_type``, e.g. ``std_msgs::msg::dds_::Float64_``."""
    return msg_type.__idl_typename__.replace(".", "::")


def ros_type_name(msg_type: type[IdlStruct]) -> str:
    """Return the ROS 2 name of ``msg_type``, e.g. ``std_msgs/msg/Float64``."""
    package, msg, _dds, name = dds_type_name(msg_type).split("::")
    return f"{package}/{msg}/{name.removesuffix('_')}"


def time_from_ns(stamp_ns: int) -> Time:
    """Split integer nanoseconds into a ROS 2 ``Time`` (``sec``, ``nanosec``).

    Negative stamps keep ``0 <= nanosec < 1e9`` as ROS 2 requires (floor division).
    """
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def time_to_ns(stamp: Time) -> int:
    """Return a ROS 2 ``Time`` as integer nanoseconds."""
    return stamp.sec * NS_PER_S + stamp.nanosec


def _floats(values: Iterable[float]) -> list[float]:
    # The serializer wants a list of Python floats; tolist() converts numpy arrays fast.
    tolist = getattr(values, "tolist", None)
    return [float(v) for v in (tolist() if tolist else values)]


def float64_multi_array(values: Iterable[float], label: str = "") -> Float64MultiArray:
    """Build a one-dimensional ``Float64MultiArray`` holding ``values``.

    Args:
        values: the doubles to send (list, tuple or numpy array).
        label: name of the single dimension; empty leaves the layout empty, as
            ``ros2 topic pub`` does.
    """
    data = _floats(values)
    layout = MultiArrayLayout()
    if label:
        layout.dim.append(MultiArrayDimension(label=label, size=len(data), stride=len(data)))
    return Float64MultiArray(layout=layout, data=data)


def joint_state(
    names: Sequence[str],
    positions: Iterable[float],
    stamp_ns: int,
    frame_id: str = "",
) -> JointState:
    """Build a ``JointState`` with positions only (velocity and effort left empty).

    Args:
        names: joint names, one per position.
        positions: joint positions (rad or m, as ROS 2 REP 103).
        stamp_ns: time stamp in integer nanoseconds since the epoch of its clock.
        frame_id: frame of the header, usually empty for joint states.

    Raises:
        ValueError: ``names`` and ``positions`` differ in length.
    """
    position = _floats(positions)
    if len(names) != len(position):
        raise ValueError(f"joint_state: {len(names)} names but {len(position)} positions")
    header = Header(stamp=time_from_ns(stamp_ns), frame_id=frame_id)
    return JointState(header=header, name=list(names), position=position)
