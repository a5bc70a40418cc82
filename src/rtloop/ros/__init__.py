"""ROS 2 over DDS: message types, publishers/subscribers and input validation.

Importing this package never fails for lack of ``cyclonedds`` or ``rclpy``; creating
a :class:`RosPublisher` or :class:`RosSubscriber` without either raises
:class:`RosUnavailable` saying what to install.
"""

from .dds import QOS_PRESETS as QOS_PRESETS
from .dds import RosPublisher as RosPublisher
from .dds import RosSubscriber as RosSubscriber
from .dds import dds_topic_name as dds_topic_name
from .errors import RosConfigError as RosConfigError
from .errors import RosUnavailable as RosUnavailable
from .errors import domain_id_from_env as domain_id_from_env
from .messages import Float64 as Float64
from .messages import Float64MultiArray as Float64MultiArray
from .messages import Header as Header
from .messages import JointState as JointState
from .messages import MultiArrayDimension as MultiArrayDimension
from .messages import MultiArrayLayout as MultiArrayLayout
from .messages import Time as Time
from .messages import float64_multi_array as float64_multi_array
from .messages import joint_state as joint_state
from .messages import time_from_ns as time_from_ns
from .messages import time_to_ns as time_to_ns
from .validate import MessageValidator as MessageValidator
from .validate import RateLimitedWarner as RateLimitedWarner
from .validate import RejectCounts as RejectCounts
from .validate import RejectedValues as RejectedValues
from .validate import validate_values as validate_values

__all__ = [
    "QOS_PRESETS",
    "Float64",
    "Float64MultiArray",
    "Header",
    "JointState",
    "MessageValidator",
    "MultiArrayDimension",
    "MultiArrayLayout",
    "RateLimitedWarner",
    "RejectCounts",
    "RejectedValues",
    "RosConfigError",
    "RosPublisher",
    "RosSubscriber",
    "RosUnavailable",
    "Time",
    "dds_topic_name",
    "domain_id_from_env",
    "float64_multi_array",
    "joint_state",
    "time_from_ns",
    "time_to_ns",
    "validate_values",
]
