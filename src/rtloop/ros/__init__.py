"""ROS 2 over DDS: message types, publishers/subscribers and input validation.

Importing this package never fails for lack of ``cyclonedds`` or ``rclpy``; creating
a :class:`RosPublisher` or :class:`RosSubscriber` without either raises
:class:`RosUnavailable` saying what to install.
"""
