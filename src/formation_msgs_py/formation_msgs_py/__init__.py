"""The messages of the formation: what travels between the processes and how.

:mod:`topics` (names, docs/topics.md), :mod:`codec` (a message's CDR bytes to and from numbers, without
rclpy: the agents, the simulator's witness and the bag tools decode with the same code), the checks
a message must pass before anything is computed from it (:mod:`measurement_checks`: what an agent
receives; :mod:`wrench_checks`: what the simulator receives), and in :mod:`formation_msgs_py.ros` the
QoS profiles and the conversions to and from ROS message objects.
"""
