"""The launcher of a ROS 2 run: process supervisor, DDS environment and the formation-launch command."""
