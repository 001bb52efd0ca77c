"""numpy ⇄ ROS message conversions, one function per message type and direction.

geometry_msgs quaternions are fields (x, y, z, w); our rotations are 3×3 row-major matrices,
converted by :func:`formation_msgs_py.so3.quaternion_from_matrix` and its inverse only. Time
stamps are float seconds on our side and (sec, nanosec) on the wire; simulation times are
multiples of the control period, so :func:`stamp_from_seconds` rounds to the nanosecond
and :func:`seconds_from_stamp` maps it back to the same float.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, PoseArray, TransformStamped, TwistStamped, WrenchStamped
from rosgraph_msgs.msg import Clock

from formation_msgs_py import topics
from formation_msgs_py.so3 import matrix_from_quaternion, quaternion_from_matrix

NS_PER_S = 1_000_000_000


def stamp_from_seconds(t: float) -> Time:
    ns = round(t * NS_PER_S)
    return Time(sec=ns // NS_PER_S, nanosec=ns % NS_PER_S)


def seconds_from_stamp(stamp: Time) -> float:
    return stamp.sec + stamp.nanosec / NS_PER_S


def stamp_ns(stamp: Time) -> int:
    """A stamp as integer nanoseconds (exact: use it to match steps)."""
    return stamp.sec * NS_PER_S + stamp.nanosec


def relative_pose_to_msg(
    t: float, observer: str, target: str, p_i_j_in_i: Sequence[float], R_i_j: Sequence[Sequence[float]]
) -> TransformStamped:
    msg = TransformStamped()
    msg.header.stamp = stamp_from_seconds(t)
    msg.header.frame_id = topics.agent_frame(observer)
    msg.child_frame_id = topics.agent_frame(target)
    tr = msg.transform.translation
    tr.x, tr.y, tr.z = (float(c) for c in p_i_j_in_i)
    q = msg.transform.rotation
    q.x, q.y, q.z, q.w = quaternion_from_matrix(R_i_j)
    return msg


def relative_pose_from_msg(msg: TransformStamped) -> tuple[list[float], list[list[float]]]:
    """(p_i_j_in_i, R_i_j) as Python lists, the form the controller reads fastest."""
    tr = msg.transform.translation
    q = msg.transform.rotation
    return [tr.x, tr.y, tr.z], matrix_from_quaternion(q.x, q.y, q.z, q.w)


def twist_to_msg(t: float, agent_id: str, v: Sequence[float]) -> TwistStamped:
    msg = TwistStamped()
    msg.header.stamp = stamp_from_seconds(t)
    msg.header.frame_id = topics.agent_frame(agent_id)
    lin, ang = msg.twist.linear, msg.twist.angular
    lin.x, lin.y, lin.z, ang.x, ang.y, ang.z = (float(c) for c in v)
    return msg


def twist_from_msg(msg: TwistStamped) -> list[float]:
    lin, ang = msg.twist.linear, msg.twist.angular
    return [lin.x, lin.y, lin.z, ang.x, ang.y, ang.z]


def wrench_to_msg(stamp: Time, agent_id: str, u: Sequence[float]) -> WrenchStamped:
    msg = WrenchStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = topics.agent_frame(agent_id)
    f, tq = msg.wrench.force, msg.wrench.torque
    f.x, f.y, f.z, tq.x, tq.y, tq.z = (float(c) for c in u)
    return msg


def wrench_from_msg(msg: WrenchStamped) -> list[float]:
    f, tq = msg.wrench.force, msg.wrench.torque
    return [f.x, f.y, f.z, tq.x, tq.y, tq.z]


def poses_to_msg(t: float, p, R) -> PoseArray:
    """Ground truth: world poses of every agent, in formation-file order."""
    msg = PoseArray()
    msg.header.stamp = stamp_from_seconds(t)
    msg.header.frame_id = topics.WORLD_FRAME
    poses = []
    for pi, Ri in zip(p.tolist(), R.tolist()):
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = pi
        o = pose.orientation
        o.x, o.y, o.z, o.w = quaternion_from_matrix(Ri)
        poses.append(pose)
    msg.poses = poses
    return msg


def poses_from_msg(msg: PoseArray) -> tuple[list[list[float]], list[list[list[float]]]]:
    """(p (N,3), R (N,3,3)) as nested lists from a ground-truth PoseArray."""
    p = [[ps.position.x, ps.position.y, ps.position.z] for ps in msg.poses]
    R = [
        matrix_from_quaternion(ps.orientation.x, ps.orientation.y, ps.orientation.z, ps.orientation.w)
        for ps in msg.poses
    ]
    return p, R


def clock_msg(t: float) -> Clock:
    return Clock(clock=stamp_from_seconds(t))


# --- hot paths: fill pre-allocated messages in place (nodes publish thousands per second) -------


def stamp_from_ns(ns: int) -> Time:
    """A stamp from integer nanoseconds (exact)."""
    return Time(sec=ns // NS_PER_S, nanosec=ns % NS_PER_S)


def set_stamp_ns(stamp: Time, ns: int) -> None:
    """Write integer nanoseconds into an existing stamp (no allocation)."""
    stamp.sec = ns // NS_PER_S
    stamp.nanosec = ns % NS_PER_S


def fill_relative_pose(msg: TransformStamped, p_i_j_in_i: Sequence[float], R_i_j: Sequence[Sequence[float]]) -> None:
    """Overwrite translation (m, frame agent_i) and rotation R_i_j of a TransformStamped."""
    tr = msg.transform.translation
    tr.x, tr.y, tr.z = p_i_j_in_i
    q = msg.transform.rotation
    q.x, q.y, q.z, q.w = quaternion_from_matrix(R_i_j)


def fill_twist(msg: TwistStamped, v: Sequence[float]) -> None:
    """Overwrite the twist [vx, vy, vz, wx, wy, wz] (body frame) of a TwistStamped."""
    lin, ang = msg.twist.linear, msg.twist.angular
    lin.x, lin.y, lin.z, ang.x, ang.y, ang.z = v


def fill_wrench(msg: WrenchStamped, u: Sequence[float]) -> None:
    """Overwrite the wrench [fx, fy, fz, tx, ty, tz] (body frame, N and N·m) of a WrenchStamped."""
    f, tq = msg.wrench.force, msg.wrench.torque
    f.x, f.y, f.z, tq.x, tq.y, tq.z = u


def relative_pose_template(observer: str, target: str) -> TransformStamped:
    """A TransformStamped with frame names set (``agent_<observer>`` -> ``agent_<target>``)."""
    msg = TransformStamped()
    msg.header.frame_id = topics.agent_frame(observer)
    msg.child_frame_id = topics.agent_frame(target)
    return msg


def twist_template(agent_id: str) -> TwistStamped:
    msg = TwistStamped()
    msg.header.frame_id = topics.agent_frame(agent_id)
    return msg


def wrench_template(agent_id: str) -> WrenchStamped:
    msg = WrenchStamped()
    msg.header.frame_id = topics.agent_frame(agent_id)
    return msg


# --- hot paths without message objects: serialized CDR (what rclpy's raw publish/subscribe use) ---
#
# rclpy builds a Python object for every nested message it takes (Header, Time, Vector3, …:
# ~70 µs per WrenchStamped here) and converts every published object field by field. The nodes'
# per-step messages are fixed-layout, so they are written and read as CDR bytes instead
# (little-endian PLAIN_CDR, 4-byte encapsulation header, alignment counted after it). Layout of
# every stamped type used here: int32 sec, uint32 nanosec, the message's strings (uint32 length
# including the NUL, bytes, NUL; 4-aligned), then float64 fields (8-aligned). Checked against
# rclpy.serialization in tests/ros/test_conversions_cdr.py.

_CDR_LE = b"\x00\x01\x00\x00"
_STAMP = struct.Struct("<iI")
_U32 = struct.Struct("<I")


class StampedCodec:
    """Encode/decode one stamped message type with fixed strings: stamp + ``n_doubles`` float64.

    ``strings`` are the message's string fields in order (header.frame_id, then e.g.
    child_frame_id); the doubles follow in declaration order (TwistStamped: linear xyz, angular
    xyz; WrenchStamped: force, torque; TransformStamped: translation xyz, rotation xyzw).
    """

    def __init__(self, strings: Sequence[str], n_doubles: int) -> None:
        mid = b""
        off = 8  # after sec, nanosec
        for s in strings:
            raw = s.encode("utf-8") + b"\0"
            pad = (-off) % 4
            mid += b"\0" * pad + _U32.pack(len(raw)) + raw
            off += pad + 4 + len(raw)
        pad = (-off) % 8
        mid += b"\0" * pad
        self.n_strings = len(strings)
        self.n_doubles = n_doubles
        self._pack = struct.Struct(f"<4siI{len(mid)}s{n_doubles}d").pack
        self._mid = mid
        self._doubles = struct.Struct(f"<{n_doubles}d")

    def encode(self, ns: int, values: Sequence[float]) -> bytes:
        """CDR bytes of the message stamped ``ns`` (integer nanoseconds) carrying ``values``."""
        sec, nsec = divmod(ns, NS_PER_S)
        return self._pack(_CDR_LE, sec, nsec, self._mid, *values)

    def decode(self, data: bytes) -> tuple[int, tuple[float, ...]]:
        """(stamp in integer ns, the doubles) of CDR bytes of this type (any string contents)."""
        sec, nsec = _STAMP.unpack_from(data, 4)
        off = 8
        for _ in range(self.n_strings):
            off += (-off) % 4
            off += 4 + _U32.unpack_from(data, 4 + off)[0]
        off += (-off) % 8
        return sec * NS_PER_S + nsec, self._doubles.unpack_from(data, 4 + off)


def twist_codec(agent_id: str) -> StampedCodec:
    """TwistStamped in frame ``agent_<id>``: [vx, vy, vz, wx, wy, wz]."""
    return StampedCodec([topics.agent_frame(agent_id)], 6)


def wrench_codec(agent_id: str) -> StampedCodec:
    """WrenchStamped in frame ``agent_<id>``: [fx, fy, fz, tx, ty, tz]."""
    return StampedCodec([topics.agent_frame(agent_id)], 6)


def relative_pose_codec(observer: str, target: str) -> StampedCodec:
    """TransformStamped ``agent_<observer>`` -> ``agent_<target>``: translation xyz, quaternion xyzw."""
    return StampedCodec([topics.agent_frame(observer), topics.agent_frame(target)], 7)


def clock_bytes(ns: int) -> bytes:
    """CDR bytes of a rosgraph_msgs/Clock at ``ns`` (integer nanoseconds)."""
    sec, nsec = divmod(ns, NS_PER_S)
    return _CDR_LE + _STAMP.pack(sec, nsec)


def relative_pose_values(p_i_j_in_i: Sequence[float], R_i_j: Sequence[Sequence[float]]) -> tuple[float, ...]:
    """The 7 doubles of a relative pose: translation (m, frame agent_i) and quaternion (x, y, z, w)."""
    return (*p_i_j_in_i, *quaternion_from_matrix(R_i_j))


def relative_pose_from_values(values: Sequence[float]) -> tuple[list[float], list[list[float]]]:
    """(p_i_j_in_i, R_i_j) as Python lists from the 7 doubles of :func:`relative_pose_values`."""
    px, py, pz, qx, qy, qz, qw = values
    return [px, py, pz], matrix_from_quaternion(qx, qy, qz, qw)
