"""The CDR codecs of formation_msgs_py.ros.conversions agree with rclpy's own serialization."""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped, TransformStamped, TwistStamped, WrenchStamped
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock

from formation_msgs_py.ros import conversions as cv

STAMPS = [0, 1, 999_999_999, 1_000_000_000, 12_345_678_901_234, 2**31 * 1_000_000_000 - 1]


def test_twist_and_wrench_round_trip_through_rclpy() -> None:
    """Encoded twists/wrenches deserialize in rclpy; rclpy's bytes decode to the same values."""
    rng = np.random.default_rng(0)
    for agent in ("1", "agent_long_name_17", "x"):
        for codec, msg_type in ((cv.twist_codec(agent), TwistStamped), (cv.wrench_codec(agent), WrenchStamped)):
            for ns in STAMPS:
                vals = tuple(rng.normal(size=6).tolist())
                msg = deserialize_message(codec.encode(ns, vals), msg_type)
                assert cv.stamp_ns(msg.header.stamp) == ns
                assert msg.header.frame_id == f"agent_{agent}"
                got = cv.twist_from_msg(msg) if msg_type is TwistStamped else cv.wrench_from_msg(msg)
                assert tuple(got) == vals
                assert codec.decode(serialize_message(msg)) == (ns, vals)


def test_relative_pose_round_trip_through_rclpy() -> None:
    """PoseStamped in the observer's frame: position and quaternion (x, y, z, w) in geometry_msgs order."""
    from formation_core.so3 import exp_so3

    rng = np.random.default_rng(1)
    for obs in ("1", "10", "abc", "defgh"):
        codec = cv.relative_pose_codec(obs)
        p = rng.normal(size=3).tolist()
        R = exp_so3(rng.normal(size=3)).tolist()
        data = codec.encode(5_000_100, cv.relative_pose_values(p, R))
        msg = deserialize_message(data, PoseStamped)
        ref = cv.relative_pose_to_msg(0.0050001, obs, p, R)
        assert msg.header.frame_id == f"agent_{obs}"
        assert msg == ref
        ns, vals = codec.decode(serialize_message(ref))
        assert ns == 5_000_100
        p2, R2 = cv.relative_pose_from_values(vals)
        assert p2 == p
        # through the quaternion and back: +, ×, ÷ and sqrt only, each correctly rounded on every IEEE
        # machine, about ten on entries ≤ 1 each way: under 1e-15 = 4.5 ulp(1) here and everywhere
        assert max(abs(a - b) for ra, rb in zip(R, R2) for a, b in zip(ra, rb)) < 1e-15


def test_relative_pose_decoder_reads_old_transform_stamped() -> None:
    """Bags recorded before PoseStamped hold TransformStamped relative poses: the decoder reads both alike."""
    from formation_core.so3 import exp_so3

    rng = np.random.default_rng(3)
    p = rng.normal(size=3).tolist()
    R = exp_so3(rng.normal(size=3)).tolist()
    pose = cv.relative_pose_to_msg(1.5, "1", p, R)
    old = TransformStamped()
    old.header = pose.header
    old.child_frame_id = "agent_2"
    tr, q = old.transform.translation, old.transform.rotation
    tr.x, tr.y, tr.z = pose.pose.position.x, pose.pose.position.y, pose.pose.position.z
    o = pose.pose.orientation
    q.x, q.y, q.z, q.w = o.x, o.y, o.z, o.w
    assert cv.relative_pose_from_msg(old) == cv.relative_pose_from_msg(pose)
    assert cv.relative_pose_from_msg(pose)[0] == p


def test_clock_bytes() -> None:
    """/clock as CDR bytes."""
    for ns in STAMPS:
        msg = deserialize_message(cv.clock_bytes(ns), Clock)
        assert cv.stamp_ns(msg.clock) == ns


def test_ground_truth_bytes_deserialize_in_rclpy() -> None:
    """The ground-truth PoseArray as CDR bytes: stamp, frame 'world', one pose per agent, any count."""
    from formation_core.rotations import quaternion_from_matrix
    from formation_core.so3 import exp_so3

    rng = np.random.default_rng(2)
    for n in (0, 1, 5, 50):
        p = rng.normal(size=(n, 3)).tolist()
        R = [exp_so3(theta).tolist() for theta in rng.normal(size=(n, 3))]
        msg = deserialize_message(cv.ground_truth_bytes(12_345_678_901, p, R), PoseArray)
        assert cv.stamp_ns(msg.header.stamp) == 12_345_678_901
        assert msg.header.frame_id == "world"
        assert len(msg.poses) == n
        for pose, pi, Ri in zip(msg.poses, p, R):
            o = pose.orientation
            assert [pose.position.x, pose.position.y, pose.position.z] == pi
            assert [o.x, o.y, o.z, o.w] == list(quaternion_from_matrix(Ri))
