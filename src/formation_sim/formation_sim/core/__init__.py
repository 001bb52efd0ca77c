"""The ROS-free world and closed loop: plant, signals, measurements, the agents stepped together, the
compiled run core, rates, accepted inputs, pre-flight and the run recorder. Never imports rclpy."""
