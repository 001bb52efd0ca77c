"""The docs/topics.md topics without ROS: names, types, and CDR <-> Python values via rosbags.

Decoding uses the agent node's own decoders and CDR codecs (:mod:`formation_msgs_py.codec`, no
ROS import), so a relative pose decoded here gives the controller exactly the numbers the agent
node saw. Relative poses are geometry_msgs/PoseStamped; bags recorded when they were
TransformStamped (same numbers, plus a child frame name) are still read.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from formation_bag.writer import typestore
from formation_core.rotations import quaternion_from_matrix
from formation_msgs_py import codec, topics
from formation_msgs_py.codec import NS_PER_S, stamp_ns
from formation_msgs_py.codec import control_time as seconds  # noqa: F401 - a stamp's time, as an agent's

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
#: the relative poses' type in bags recorded before they became PoseStamped (still read)
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
CLOCK = "rosgraph_msgs/msg/Clock"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"


@dataclass(frozen=True)
class TopicKind:
    """What a topic name means: ``kind`` in relative_pose/velocity/wrench/ground_truth/clock/diagnostics."""

    kind: str
    msgtype: str
    agent: str | None = None
    target: str | None = None


_RE_REL = re.compile(r"^(?P<ns>.*?)/?agent_(?P<i>[^/]+)/relative_pose/agent_(?P<j>[^/]+)$")
_RE_VEL = re.compile(r"^(?P<ns>.*?)/?agent_(?P<i>[^/]+)/velocity$")
_RE_WRENCH = re.compile(r"^(?P<ns>.*?)/?agent_(?P<i>[^/]+)/wrench$")


def absolute(name: str, namespace: str = "") -> str:
    """Resolve a docs/topics.md topic name (relative or absolute) in ``namespace``."""
    if name.startswith("/"):
        return name
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{name}"


def classify(topic: str, namespace: str = "") -> TopicKind | None:
    """The meaning of a recorded topic name, or None if it is not a docs/topics.md topic."""
    if topic == topics.CLOCK:
        return TopicKind("clock", CLOCK)
    if topic == topics.DIAGNOSTICS:
        return TopicKind("diagnostics", DIAGNOSTIC_ARRAY)
    if topic == absolute(topics.GROUND_TRUTH, namespace):
        return TopicKind("ground_truth", POSE_ARRAY)
    prefix = absolute("", namespace).rstrip("/")
    if prefix and not topic.startswith(prefix + "/"):
        return None
    rest = topic[len(prefix) :]
    if m := _RE_REL.match(rest):
        if m["ns"]:
            return None
        return TopicKind("relative_pose", POSE_STAMPED, m["i"], m["j"])
    if (m := _RE_VEL.match(rest)) and not m["ns"]:
        return TopicKind("velocity", TWIST_STAMPED, m["i"])
    if (m := _RE_WRENCH.match(rest)) and not m["ns"]:
        return TopicKind("wrench", WRENCH_STAMPED, m["i"])
    return None


def formation_topics(agent_ids: Sequence[str], edges: Sequence[tuple[str, str]], namespace: str = "") -> dict[str, str]:
    """Every docs/topics.md topic of a formation: {absolute name: type}."""
    out = {
        topics.CLOCK: CLOCK,
        absolute(topics.GROUND_TRUTH, namespace): POSE_ARRAY,
        topics.DIAGNOSTICS: DIAGNOSTIC_ARRAY,
        absolute(topics.MARKERS, namespace): MARKER_ARRAY,  # for viewers; not analysed
        absolute(topics.FUNNELS, namespace): FLOAT64_MULTI_ARRAY,  # for plots; not analysed
    }
    for a in agent_ids:
        out[absolute(topics.velocity(a), namespace)] = TWIST_STAMPED
        out[absolute(topics.wrench(a), namespace)] = WRENCH_STAMPED
    for tail, head in edges:
        out[absolute(topics.relative_pose(tail, head), namespace)] = POSE_STAMPED
        out[absolute(topics.relative_pose(head, tail), namespace)] = POSE_STAMPED
    return out


# -- decoding -------------------------------------------------------------------------------------


def deserialize(data: bytes | memoryview, msgtype: str) -> Any:
    return typestore().deserialize_cdr(data, msgtype)


# the agent node's own decoders (by field name, so rosbags messages work too)
decode_relative_pose = codec.relative_pose_from_msg
decode_twist = codec.twist_from_msg
decode_wrench = codec.wrench_from_msg
decode_poses = codec.poses_from_msg


# -- fast decoding of the fixed-layout messages (little-endian CDR), same numbers as rosbags ---------

# the nodes' codecs (formation_msgs_py.codec); decoding ignores the frame names
_POSE_CODEC = codec.StampedCodec([""], 7)  # PoseStamped: header.frame_id, then position, orientation
_OLD_POSE_CODEC = codec.StampedCodec(["", ""], 7)  # TransformStamped: frame_id and child_frame_id
_SIX_CODEC = codec.StampedCodec([""], 6)


def _doubles_of(kind: str, obj: Any) -> tuple[float, ...]:
    """The doubles of a deserialized message, in the order of its CDR (see :func:`fast_values`)."""
    if kind == "relative_pose":
        pose = getattr(obj, "pose", None)  # None: a TransformStamped of an older bag
        if pose is None:
            pos, q = obj.transform.translation, obj.transform.rotation
        else:
            pos, q = pose.position, pose.orientation
        return (pos.x, pos.y, pos.z, q.x, q.y, q.z, q.w)
    if kind == "velocity":
        return tuple(decode_twist(obj))
    if kind == "wrench":
        return tuple(decode_wrench(obj))
    if kind == "ground_truth":
        return tuple(
            x for ps in obj.poses for x in (ps.position.x, ps.position.y, ps.position.z, *_xyzw(ps.orientation))
        )
    raise ValueError(f"no decoder for {kind!r}")


def _xyzw(q: Any) -> tuple[float, float, float, float]:
    return q.x, q.y, q.z, q.w


def fast_values(kind: str, data: bytes | memoryview, msgtype: str) -> tuple[int, tuple[float, ...]]:
    """(stamp ns, the message's doubles) of a docs/topics.md message; rosbags for anything but
    little-endian CDR. Doubles: relative_pose 7 (position, quaternion xyzw), velocity/wrench 6,
    ground_truth 7 per agent, clock none; :data:`FROM_VALUES` turns them into the decoded values.
    """
    if len(data) < 12 or data[1] != 1:
        obj = deserialize(data, msgtype)
        if kind == "clock":
            return stamp_ns(obj.clock), ()
        return stamp_ns(obj.header.stamp), _doubles_of(kind, obj)
    if kind == "clock":
        return codec.stamp_of(data), ()
    if kind == "relative_pose":
        return (_OLD_POSE_CODEC if msgtype == TRANSFORM_STAMPED else _POSE_CODEC).decode(data)
    if kind in ("velocity", "wrench"):
        return _SIX_CODEC.decode(data)
    if kind == "ground_truth":
        return codec.ground_truth_values(data)
    raise ValueError(f"no fast decoder for {kind!r}")


def pose_stamped_from_transform(data: bytes | memoryview, observer: str) -> bytes:
    """An older bag's TransformStamped relative pose as the PoseStamped the agents now take (same
    stamp and numbers, frame ``agent_<observer>``): what formation-replay publishes for it."""
    stamp, values = fast_values("relative_pose", data, TRANSFORM_STAMPED)
    return codec.relative_pose_codec(observer).encode(stamp, values)


#: the decoded value of a message from its doubles, per kind (the agent node's own decoders)
FROM_VALUES: dict[str, Callable[[Sequence[float]], Any]] = {
    "relative_pose": codec.relative_pose_from_values,
    "velocity": list,
    "wrench": list,
    "ground_truth": codec.ground_truth_from_values,
}


def fast_decode(kind: str, data: bytes | memoryview, msgtype: str) -> tuple[int, Any]:
    """(stamp ns, value) of a docs/topics.md message; rosbags for anything but little-endian CDR.

    value: relative_pose -> (p, R), velocity/wrench -> 6 floats, ground_truth -> (p (N,3), R (N,3,3)),
    clock -> None. Identical numbers to rosbags' deserialize + the decode_* functions.
    """
    stamp, values = fast_values(kind, data, msgtype)
    return stamp, (None if kind == "clock" else FROM_VALUES[kind](values))


# -- encoding (for bags written without ROS: synthetic runs, tests) -------------------------------


class Encoder:
    """Serialize the docs/topics.md messages with rosbags (same fields as conversions.*_to_msg)."""

    def __init__(self) -> None:
        ts = typestore()
        self.ts = ts
        t = ts.types
        self.Time = t["builtin_interfaces/msg/Time"]
        self.Header = t["std_msgs/msg/Header"]
        self.Vector3 = t["geometry_msgs/msg/Vector3"]
        self.Quaternion = t["geometry_msgs/msg/Quaternion"]
        self.Point = t["geometry_msgs/msg/Point"]
        self.Pose = t["geometry_msgs/msg/Pose"]
        self.PoseStamped = t[POSE_STAMPED]
        self.Twist = t["geometry_msgs/msg/Twist"]
        self.TwistStamped = t[TWIST_STAMPED]
        self.Wrench = t["geometry_msgs/msg/Wrench"]
        self.WrenchStamped = t[WRENCH_STAMPED]
        self.PoseArray = t[POSE_ARRAY]
        self.Clock = t[CLOCK]

    def time(self, ns: int) -> Any:
        sec, nsec = divmod(ns, NS_PER_S)
        return self.Time(sec=sec, nanosec=nsec)

    def header(self, ns: int, frame: str) -> Any:
        return self.Header(stamp=self.time(ns), frame_id=frame)

    def clock(self, ns: int) -> bytes:
        return bytes(self.ts.serialize_cdr(self.Clock(clock=self.time(ns)), CLOCK))

    def relative_pose(
        self,
        ns: int,
        observer: str,
        p: Sequence[float] | np.ndarray,
        q: Sequence[float] | np.ndarray,
    ) -> bytes:
        """PoseStamped in frame ``agent_<observer>``: position p (m) and orientation, the quaternion q
        (x, y, z, w), of the neighbour."""
        x, y, z, w = (float(c) for c in q)
        msg = self.PoseStamped(
            header=self.header(ns, topics.agent_frame(observer)),
            pose=self.Pose(
                position=self.Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=self.Quaternion(x=x, y=y, z=z, w=w),
            ),
        )
        return bytes(self.ts.serialize_cdr(msg, POSE_STAMPED))

    def twist(self, ns: int, agent: str, v: Sequence[float]) -> bytes:
        v = [float(c) for c in v]
        msg = self.TwistStamped(
            header=self.header(ns, topics.agent_frame(agent)),
            twist=self.Twist(linear=self.Vector3(x=v[0], y=v[1], z=v[2]), angular=self.Vector3(x=v[3], y=v[4], z=v[5])),
        )
        return bytes(self.ts.serialize_cdr(msg, TWIST_STAMPED))

    def wrench(self, ns: int, agent: str, u: Sequence[float]) -> bytes:
        u = [float(c) for c in u]
        msg = self.WrenchStamped(
            header=self.header(ns, topics.agent_frame(agent)),
            wrench=self.Wrench(force=self.Vector3(x=u[0], y=u[1], z=u[2]), torque=self.Vector3(x=u[3], y=u[4], z=u[5])),
        )
        return bytes(self.ts.serialize_cdr(msg, WRENCH_STAMPED))

    def empty(self, ns: int, msgtype: str) -> bytes:
        """A /diagnostics, markers or funnels message with nothing in it (stamped ``ns`` where it has a header)."""
        t = self.ts.types
        if msgtype == DIAGNOSTIC_ARRAY:
            msg = t[msgtype](header=self.header(ns, ""), status=[])
        elif msgtype == MARKER_ARRAY:
            msg = t[msgtype](markers=[])
        elif msgtype == FLOAT64_MULTI_ARRAY:
            layout = t["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
            msg = t[msgtype](layout=layout, data=np.zeros(0))
        else:
            raise ValueError(f"no empty message of type {msgtype}")
        return bytes(self.ts.serialize_cdr(msg, msgtype))

    def poses(self, ns: int, p: Sequence[Sequence[float]], R: Sequence[Sequence[Sequence[float]]]) -> bytes:
        poses = []
        for pi, Ri in zip(p, R):
            x, y, z, w = quaternion_from_matrix(Ri)
            poses.append(
                self.Pose(
                    position=self.Point(x=float(pi[0]), y=float(pi[1]), z=float(pi[2])),
                    orientation=self.Quaternion(x=x, y=y, z=z, w=w),
                )
            )
        msg = self.PoseArray(header=self.header(ns, topics.WORLD_FRAME), poses=poses)
        return bytes(self.ts.serialize_cdr(msg, POSE_ARRAY))
