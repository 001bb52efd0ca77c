"""QoS profiles of every topic, defined once (DESIGN.md §3). Imports rclpy: nodes only.

- ``CONTROL``: measurements and wrenches. Reliable, keep last 10, volatile: in lockstep a
  lost message would stall a step until its timeout; on one host reliability is cheap.
- ``CLOCK``: /clock, reliable keep-last-1 publisher (compatible with rclpy's best-effort
  time-source subscription).
- ``GROUND_TRUTH``: reliable, keep last 100 (recorders may lag a little).
- ``DIAGNOSTICS``: reliable, keep last 10 (the ROS default).
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

CONTROL = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
CLOCK = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
GROUND_TRUTH = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
DIAGNOSTICS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
