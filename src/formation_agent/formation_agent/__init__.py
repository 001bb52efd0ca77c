"""The agent of a formation: the prescribed-performance controller (ROS-free) and its node."""
