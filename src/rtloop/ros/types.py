"""ROS 2 names rtloop uses (a leaf: the app description and the recorders check against it).

The message types bridges carry; the topics and ``ros2msg`` schemas of a run's recorded
signals and timing, shared by ``run.mcap`` and the Foxglove live view.
"""

import re

ROS_TYPES = ("std_msgs/msg/Float64MultiArray", "std_msgs/msg/Float64", "sensor_msgs/msg/JointState")


SIGNALS_TOPIC = "/rtloop/signals"
TIMING_TOPIC_PREFIX = "/rtloop/timing/"
SIGNAL_TOPIC_PREFIX = "/rtloop/signal/"
NS_PER_S = 1_000_000_000

_SEPARATOR = "\n" + "=" * 80 + "\n"
_TIME_MSG = "int32 sec\nuint32 nanosec\n"
_HEADER_MSG = "builtin_interfaces/Time stamp\nstring frame_id\n"
JOINT_STATE_SCHEMA = (
    "std_msgs/Header header\n"
    "string[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n"
    + _SEPARATOR + "MSG: std_msgs/Header\n" + _HEADER_MSG
    + _SEPARATOR + "MSG: builtin_interfaces/Time\n" + _TIME_MSG
)
FLOAT64_SCHEMA = "float64 data\n"
CYCLE_TIMING_SCHEMA = (
    "# One cycle of an rtloop task; times are CLOCK_MONOTONIC nanoseconds (timing.csv).\n"
    "uint64 cycle\n"
    "int64 release_ns\n"
    "int64 start_ns\n"
    "int64 end_ns\n"
    "# start_ns - release_ns: wake-up latency, as cyclictest measures it\n"
    "int64 latency_ns\n"
    "# end_ns - start_ns: time spent reading inputs, stepping and publishing\n"
    "int64 exec_ns\n"
)


def topic_token(name: str) -> str:
    """Turn a task or signal name into a ROS 2 topic token: ``plant.y[0]`` → ``plant_y_0``."""
    token = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", name)).strip("_")
    return token if token and not token[0].isdigit() else f"n_{token}"
