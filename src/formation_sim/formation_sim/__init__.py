"""The world of a formation: plant, disturbances, noise, measurements (ROS-free), the
headless closed-loop runner, run reports, and the simulator node."""
