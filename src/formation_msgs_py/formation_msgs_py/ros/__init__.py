"""The few helpers that import rclpy: QoS profiles, message conversions, parameters, graph watch,
stopping. Everything else in formation_msgs_py is ROS-free."""
