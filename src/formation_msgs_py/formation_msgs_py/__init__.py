"""The messages of the formation: what travels between the processes and how.

:mod:`topics` (names, docs/topics.md), :mod:`codec` (a message's CDR bytes to and from numbers, without
rclpy: the agents, the simulator's witness and the bag tools decode with the same code), and in
:mod:`formation_msgs_py.ros` the QoS profiles and the conversions to and from ROS message objects.
"""
