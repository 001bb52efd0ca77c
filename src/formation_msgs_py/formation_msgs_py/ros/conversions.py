"""numpy ⇄ ROS message conversions, one function per message type and direction.

The decoders and the raw-CDR codecs live in :mod:`formation_msgs_py.codec` (no ROS import) and
are re-exported here.

geometry_msgs quaternions are fields (x, y, z, w); our rotations are 3×3 row-major matrices,
converted by :func:`formation_core.rotations.quaternion_from_matrix` and its inverse only. Time
stamps are float seconds on our side and (sec, nanosec) on the wire; simulation times are
multiples of the control period, so :func:`stamp_from_seconds` rounds to the nanosecond
and :func:`seconds_from_stamp` maps it back to the same float.
"""

from __future__ import annotations

from collections.abc import Sequence

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rosgraph_msgs.msg import Clock

from formation_core.rotations import quaternion_from_matrix
from formation_msgs_py import topics
from formation_msgs_py.codec import (  # noqa: F401 - the ROS-free half, re-exported for the nodes
    NS_PER_S,
    StampedCodec,
    clock_bytes,
    ground_truth_bytes,
    poses_from_msg,
    relative_pose_codec,
    relative_pose_from_msg,
    relative_pose_from_values,
    relative_pose_values,
    stamp_ns,
    twist_codec,
    twist_from_msg,
    wrench_codec,
    wrench_from_msg,
)


def stamp_from_seconds(t: float) -> Time:
    ns = round(t * NS_PER_S)
    return Time(sec=ns // NS_PER_S, nanosec=ns % NS_PER_S)


def seconds_from_stamp(stamp: Time) -> float:
    return stamp.sec + stamp.nanosec / NS_PER_S


def relative_pose_to_msg(
    t: float, observer: str, p_i_j_in_i: Sequence[float], R_i_j: Sequence[Sequence[float]]
) -> PoseStamped:
    """The pose of a neighbour in ``agent_<observer>``'s body frame (the neighbour is in the topic name)."""
    msg = PoseStamped()
    msg.header.stamp = stamp_from_seconds(t)
    msg.header.frame_id = topics.agent_frame(observer)
    pos = msg.pose.position
    pos.x, pos.y, pos.z = (float(c) for c in p_i_j_in_i)
    q = msg.pose.orientation
    q.x, q.y, q.z, q.w = quaternion_from_matrix(R_i_j)
    return msg


def twist_to_msg(t: float, agent_id: str, v: Sequence[float]) -> TwistStamped:
    msg = TwistStamped()
    msg.header.stamp = stamp_from_seconds(t)
    msg.header.frame_id = topics.agent_frame(agent_id)
    lin, ang = msg.twist.linear, msg.twist.angular
    lin.x, lin.y, lin.z, ang.x, ang.y, ang.z = (float(c) for c in v)
    return msg


def wrench_to_msg(stamp: Time, agent_id: str, u: Sequence[float]) -> WrenchStamped:
    msg = WrenchStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = topics.agent_frame(agent_id)
    f, tq = msg.wrench.force, msg.wrench.torque
    f.x, f.y, f.z, tq.x, tq.y, tq.z = (float(c) for c in u)
    return msg


def clock_msg(t: float) -> Clock:
    return Clock(clock=stamp_from_seconds(t))
