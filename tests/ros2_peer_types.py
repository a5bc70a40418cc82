"""ROS 2 message types as someone else's node declares them: plain cyclonedds, no rtloop.

Test peers (scripts run in their own process) start with :data:`ROS2_TYPES`, so they
match rtloop only if rtloop uses the ROS 2 DDS names and layouts.
"""

import textwrap

ROS2_TYPES = textwrap.dedent(
    """
    from dataclasses import dataclass
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.types import float64, int32, sequence, uint32

    @dataclass
    class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
        sec: int32
        nanosec: uint32

    @dataclass
    class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
        stamp: Time_
        frame_id: str

    @dataclass
    class JointState_(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
        header: Header_
        name: sequence[str]
        position: sequence[float64]
        velocity: sequence[float64]
        effort: sequence[float64]

    @dataclass
    class MultiArrayDimension_(IdlStruct, typename="std_msgs::msg::dds_::MultiArrayDimension_"):
        label: str
        size: uint32
        stride: uint32

    @dataclass
    class MultiArrayLayout_(IdlStruct, typename="std_msgs::msg::dds_::MultiArrayLayout_"):
        dim: sequence[MultiArrayDimension_]
        data_offset: uint32

    @dataclass
    class Float64MultiArray_(IdlStruct, typename="std_msgs::msg::dds_::Float64MultiArray_"):
        layout: MultiArrayLayout_
        data: sequence[float64]
    """
)
