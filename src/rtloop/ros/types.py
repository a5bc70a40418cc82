"""The ROS 2 message types rtloop bridges, by name (a leaf: the app description checks against it)."""

ROS_TYPES = ("std_msgs/msg/Float64MultiArray", "std_msgs/msg/Float64", "sensor_msgs/msg/JointState")
