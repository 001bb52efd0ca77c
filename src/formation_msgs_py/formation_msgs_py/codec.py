"""ROS-free halves of the message conversions: decoding by field names, and raw CDR bytes.

The decoders read fields by name, so they take rclpy messages (the nodes) and rosbags
messages (bag analysis, no ROS) alike; :mod:`formation_msgs_py.ros.conversions` re-exports them next
to the encoders that need the ROS message classes. Quaternions are converted only by
:func:`formation_core.rotations.matrix_from_quaternion` and its inverse.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Any

from formation_core.rotations import matrix_from_quaternion, quaternion_from_matrix
from formation_msgs_py import topics

NS_PER_S = 1_000_000_000


def step_stamp_ns(k: int, control_rate: float) -> int:
    """The stamp of control step ``k`` at ``control_rate`` [Hz]: round(k·10⁹/rate) integer nanoseconds.

    Every message of step k carries it, and it is the step's time for every controller (a lockstep
    or realtime agent, the simulator's shadow of it, the headless run core): :func:`control_time`.
    At a rate whose period is not a whole number of nanoseconds (3 kHz) the stamps are the period
    rounded, step by step, never drifting from k/rate by more than half a nanosecond.
    """
    return round(k * NS_PER_S / control_rate)


def control_time(ns: int) -> float:
    """The controller's time [s] of a step stamped ``ns`` (integer nanoseconds): ns / 10⁹, correctly rounded.

    An agent knows the time only from the stamps it receives; every computation that must give its
    answer (the simulator's witness, the headless run) takes the time from the stamp through this.
    """
    return ns / NS_PER_S


def stamp_ns(stamp: Any) -> int:
    """A stamp as integer nanoseconds (exact: use it to match steps)."""
    return stamp.sec * NS_PER_S + stamp.nanosec


def relative_pose_from_msg(msg: Any) -> tuple[list[float], list[list[float]]]:
    """(p_i_j_in_i, R_i_j) as Python lists, the form the controller reads fastest.

    A geometry_msgs/PoseStamped (position, orientation); a TransformStamped (translation,
    rotation: how bags recorded before the relative poses became PoseStamped hold them) is read too.
    """
    pose = getattr(msg, "pose", None)
    if pose is None:
        tr, q = msg.transform.translation, msg.transform.rotation
    else:
        tr, q = pose.position, pose.orientation
    return [tr.x, tr.y, tr.z], matrix_from_quaternion(q.x, q.y, q.z, q.w)


def twist_from_msg(msg: Any) -> list[float]:
    lin, ang = msg.twist.linear, msg.twist.angular
    return [lin.x, lin.y, lin.z, ang.x, ang.y, ang.z]


def wrench_from_msg(msg: Any) -> list[float]:
    f, tq = msg.wrench.force, msg.wrench.torque
    return [f.x, f.y, f.z, tq.x, tq.y, tq.z]


def poses_from_msg(msg: Any) -> tuple[list[list[float]], list[list[list[float]]]]:
    """(p (N,3), R (N,3,3)) as nested lists from a ground-truth PoseArray."""
    p = [[ps.position.x, ps.position.y, ps.position.z] for ps in msg.poses]
    R = [
        matrix_from_quaternion(ps.orientation.x, ps.orientation.y, ps.orientation.z, ps.orientation.w)
        for ps in msg.poses
    ]
    return p, R


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
    TransformStamped's child_frame_id); the doubles follow in declaration order (TwistStamped:
    linear xyz, angular xyz; WrenchStamped: force, torque; PoseStamped: position xyz,
    orientation xyzw).
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

    def decode(self, data: bytes | memoryview) -> tuple[int, tuple[float, ...]]:
        """(stamp in integer ns, the doubles) of CDR bytes of this type (any string contents)."""
        sec, nsec = _STAMP.unpack_from(data, 4)
        off = 8
        for _ in range(self.n_strings):
            off += (-off) % 4
            off += 4 + _U32.unpack_from(data, 4 + off)[0]
        off += (-off) % 8
        return sec * NS_PER_S + nsec, self._doubles.unpack_from(data, 4 + off)


def _ground_truth_frame() -> bytes:
    """header.frame_id of the ground truth as CDR, from offset 8 (after the stamp), padded so that
    the sequence length that follows is 4-aligned and the poses after it 8-aligned."""
    raw = topics.WORLD_FRAME.encode("utf-8") + b"\0"
    mid = _U32.pack(len(raw)) + raw
    mid += b"\0" * ((-(8 + len(mid))) % 4)
    if (8 + len(mid) + 4) % 8:
        raise AssertionError("ground-truth layout: poses would not be 8-aligned")  # fixed by WORLD_FRAME
    return mid


_GROUND_TRUTH_FRAME = _ground_truth_frame()


def twist_codec(agent_id: str) -> StampedCodec:
    """TwistStamped in frame ``agent_<id>``: [vx, vy, vz, wx, wy, wz]."""
    return StampedCodec([topics.agent_frame(agent_id)], 6)


def wrench_codec(agent_id: str) -> StampedCodec:
    """WrenchStamped in frame ``agent_<id>``: [fx, fy, fz, tx, ty, tz]."""
    return StampedCodec([topics.agent_frame(agent_id)], 6)


def relative_pose_codec(observer: str) -> StampedCodec:
    """PoseStamped in frame ``agent_<observer>`` (the target is in the topic name): position xyz,
    quaternion xyzw."""
    return StampedCodec([topics.agent_frame(observer)], 7)


def clock_bytes(ns: int) -> bytes:
    """CDR bytes of a rosgraph_msgs/Clock at ``ns`` (integer nanoseconds)."""
    sec, nsec = divmod(ns, NS_PER_S)
    return _CDR_LE + _STAMP.pack(sec, nsec)


def ground_truth_bytes(
    ns: int, p_world: Sequence[Sequence[float]], R_world: Sequence[Sequence[Sequence[float]]]
) -> bytes:
    """CDR bytes of the ground-truth geometry_msgs/PoseArray at ``ns``: frame ``world``, one pose
    per agent (position in m, orientation as quaternion x, y, z, w of R_world_body)."""
    sec, nsec = divmod(ns, NS_PER_S)
    values: list[float] = []
    for p, R in zip(p_world, R_world):
        values += p
        values += quaternion_from_matrix(R)
    head = _CDR_LE + _STAMP.pack(sec, nsec) + _GROUND_TRUTH_FRAME + _U32.pack(len(values) // 7)
    return head + struct.pack(f"<{len(values)}d", *values)


def _cdr_align(off: int, a: int) -> int:
    """CDR alignment of a byte offset: relative to the end of the 4-byte encapsulation header."""
    return 4 + ((off - 4 + a - 1) // a) * a


def ground_truth_values(data: bytes | memoryview) -> tuple[int, tuple[float, ...]]:
    """(stamp ns, 7 doubles per pose: position x, y, z, quaternion x, y, z, w) of little-endian CDR
    bytes of a geometry_msgs/PoseArray (any frame name)."""
    ns = stamp_of(data)
    off = _cdr_align(16 + _U32.unpack_from(data, 12)[0], 4)  # after header.frame_id (length, bytes)
    n = _U32.unpack_from(data, off)[0]
    off = _cdr_align(off + 4, 8)
    return ns, struct.unpack_from(f"<{7 * n}d", data, off)


def ground_truth_from_values(values: Sequence[float]) -> tuple[list[list[float]], list[list[list[float]]]]:
    """(p_world (N,3), R_world_body (N,3,3)) as Python lists from :func:`ground_truth_values`' doubles."""
    p, R = [], []
    for k in range(0, len(values), 7):
        x, y, z, qx, qy, qz, qw = values[k : k + 7]
        p.append([x, y, z])
        R.append(matrix_from_quaternion(qx, qy, qz, qw))
    return p, R


def ground_truth_from_bytes(data: bytes | memoryview) -> tuple[int, list[list[float]], list[list[list[float]]]]:
    """(stamp ns, p_world (N,3), R_world_body (N,3,3)) of little-endian CDR bytes of a
    geometry_msgs/PoseArray: the inverse of :func:`ground_truth_bytes` (any frame name)."""
    ns, values = ground_truth_values(data)
    return (ns, *ground_truth_from_values(values))


def relative_pose_values(p_i_j_in_i: Sequence[float], R_i_j: Sequence[Sequence[float]]) -> tuple[float, ...]:
    """The 7 doubles of a relative pose: position (m, frame agent_i) and quaternion (x, y, z, w)."""
    return (*p_i_j_in_i, *quaternion_from_matrix(R_i_j))


def relative_pose_from_values(values: Sequence[float]) -> tuple[list[float], list[list[float]]]:
    """(p_i_j_in_i, R_i_j) as Python lists from the 7 doubles of :func:`relative_pose_values`."""
    px, py, pz, qx, qy, qz, qw = values
    return [px, py, pz], matrix_from_quaternion(qx, qy, qz, qw)


def stamp_of(data: bytes | memoryview) -> int:
    """The stamp (integer ns) CDR bytes start with: header.stamp of every stamped message of
    docs/topics.md (and PoseArray, DiagnosticArray), or the time of a rosgraph_msgs/Clock."""
    sec, nsec = _STAMP.unpack_from(data, 4)
    return sec * NS_PER_S + nsec
