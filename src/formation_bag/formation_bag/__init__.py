"""Record, replay and analyse formation runs as standard ROS 2 bags (docs/bags.md).

ROS-free modules: :mod:`writer` (segmented rosbag2 writer), :mod:`reader` (reading, also of
bags left by a killed recorder), :mod:`messages` (the docs/topics.md topics <-> arrays),
:mod:`analysis` (``formation-analyze``), :mod:`rerun` (``formation-rerun``), :mod:`interop`
and :mod:`synth` (lockstep bags written from the headless loop, for tests and benchmarks).
The nodes :mod:`record_node` and :mod:`replay_node` import rclpy.
"""
