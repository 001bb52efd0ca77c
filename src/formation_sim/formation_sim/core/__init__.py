"""The ROS-free world and closed loop: plant, disturbances, measurements, links, the agents stepped
together, the compiled run core, rates, the plant state a run can go on with, the judge and the run
recorder. Never imports rclpy."""
