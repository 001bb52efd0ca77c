"""formation_bag.writer.offered_qos: an rclpy QoSProfile as a bag's metadata.yaml stores it, read by the
policies' names (the writer imports no rclpy)."""

from __future__ import annotations

import pytest
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import QosDurability, QosHistory, QosReliability

from formation_bag.writer import offered_qos
from formation_msgs_py.ros import qos


@pytest.mark.parametrize(
    ("history", "reliability", "durability"),
    [
        (h, r, d)
        for h in (HistoryPolicy.KEEP_LAST, HistoryPolicy.KEEP_ALL)
        for r in (ReliabilityPolicy.RELIABLE, ReliabilityPolicy.BEST_EFFORT)
        for d in (DurabilityPolicy.VOLATILE, DurabilityPolicy.TRANSIENT_LOCAL)
    ],
)
def test_every_policy_is_stored_as_offered(
    history: HistoryPolicy, reliability: ReliabilityPolicy, durability: DurabilityPolicy
) -> None:
    stored = offered_qos(QoSProfile(history=history, depth=7, reliability=reliability, durability=durability))
    assert stored.depth == 7
    assert stored.history == (QosHistory.KEEP_ALL if history == HistoryPolicy.KEEP_ALL else QosHistory.KEEP_LAST)
    reliable = reliability == ReliabilityPolicy.RELIABLE
    assert stored.reliability == (QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT)
    transient = durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert stored.durability == (QosDurability.TRANSIENT_LOCAL if transient else QosDurability.VOLATILE)


def test_the_formations_profiles() -> None:
    """The measurements' best-effort profile is stored best effort, keep last 1; the others reliable."""
    best_effort = offered_qos(qos.MEASUREMENTS_BEST_EFFORT)
    assert (best_effort.reliability, best_effort.depth) == (QosReliability.BEST_EFFORT, 1)
    for profile in (qos.CONTROL, qos.CLOCK, qos.GROUND_TRUTH, qos.DIAGNOSTICS, qos.DISPLAY):
        stored = offered_qos(profile)
        assert (stored.reliability, stored.depth) == (QosReliability.RELIABLE, profile.depth)
