"""Formation runs as standard ROS 2 bags: write, read, repair, record and replay (docs/bags.md).

ROS-free modules: :mod:`contract` (what a run's bag holds: storage names, custom_data keys),
:mod:`writer` (segmented rosbag2 writer, the one adapter to rosbags' internals), :mod:`metadata`,
:mod:`reader` (reading, also of bags left by a killed recorder), :mod:`messages` (the docs/topics.md
topics <-> arrays), :mod:`dataset` (a run decoded from its bag), :mod:`interop_check` and
:mod:`foxglove_server` (the live view over the Foxglove WebSocket protocol). The nodes
:mod:`record_node` and :mod:`replay_node` import rclpy. The offline runs from a bag
(``formation-analyze``, ``formation-rerun``) are in :mod:`formation_sim.offline`.
"""
