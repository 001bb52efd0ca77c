"""QoS profiles of every topic, defined once (docs/topics.md). Imports rclpy: nodes only.

- ``CONTROL``: measurements and wrenches. Reliable, keep last 10, volatile: in lockstep a
  lost message would stall a step until its timeout; on one host reliability is cheap.
- ``MEASUREMENTS_BEST_EFFORT``: opt-in for realtime runs (``--measurement-qos best-effort``):
  best effort, keep last 1, for relative poses and velocities only. About a third of the
  publisher's CPU per message (~35 µs instead of ~100 µs here); a lost measurement is a missed
  step (zero-order hold), which realtime tolerates and lockstep does not.
- ``CLOCK``: /clock, reliable keep-last-1 publisher (compatible with rclpy's best-effort
  time-source subscription).
- ``GROUND_TRUTH``: reliable, keep last 100 (recorders may lag a little).
- ``DIAGNOSTICS``: reliable, keep last 10 (the ROS default).
- ``DISPLAY``: markers, funnel plots and TF for viewers: reliable, keep last 10 (the ROS default;
  published at a display rate of tens of Hz, so a late viewer loses nothing it would draw).
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

CONTROL = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
MEASUREMENTS_BEST_EFFORT = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
)


def measurements(kind: str) -> QoSProfile:
    """QoS of relative poses and velocities: ``reliable`` (default, CONTROL) or ``best-effort``."""
    if kind == "reliable":
        return CONTROL
    if kind == "best-effort":
        return MEASUREMENTS_BEST_EFFORT
    raise ValueError(f"measurement QoS {kind!r} is not 'reliable' or 'best-effort'")


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
DISPLAY = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
