"""The docs/topics.md topics without ROS: names, types, and CDR <-> Python values via rosbags.

Decoding uses the agent node's own decoders and CDR codecs (:mod:`formation_msgs_py.wire`, no
ROS import), so a relative pose decoded here gives the controller exactly the numbers the agent
node saw.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from formation_msgs_py import topics, wire
from formation_msgs_py.bag.writer import typestore
from formation_msgs_py.rotations import quaternion_from_matrix
from formation_msgs_py.wire import NS_PER_S, stamp_ns

if TYPE_CHECKING:
    import numpy as np

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
        return TopicKind("relative_pose", TRANSFORM_STAMPED, m["i"], m["j"])
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
        out[absolute(topics.relative_pose(tail, head), namespace)] = TRANSFORM_STAMPED
        out[absolute(topics.relative_pose(head, tail), namespace)] = TRANSFORM_STAMPED
    return out


# -- decoding -------------------------------------------------------------------------------------


def seconds(stamp_ns_value: int) -> float:
    """Float seconds of an integer-ns stamp, as the agent node computes its controller time (ns / 1e9)."""
    return stamp_ns_value / NS_PER_S


def deserialize(data: bytes | memoryview, msgtype: str) -> Any:
    return typestore().deserialize_cdr(data, msgtype)


# the agent node's own decoders (by field name, so rosbags messages work too)
decode_relative_pose = wire.relative_pose_from_msg
decode_twist = wire.twist_from_msg
decode_wrench = wire.wrench_from_msg
decode_poses = wire.poses_from_msg


# -- fast decoding of the fixed-layout messages (little-endian CDR), same numbers as rosbags ---------

# the nodes' codecs (formation_msgs_py.wire); decoding ignores the frame names
_POSE_CODEC = wire.StampedCodec(["", ""], 7)
_SIX_CODEC = wire.StampedCodec([""], 6)


def fast_decode(kind: str, data: bytes | memoryview, msgtype: str) -> tuple[int, Any]:
    """(stamp ns, value) of a docs/topics.md message; rosbags for anything but little-endian CDR.

    value: relative_pose -> (p, R), velocity/wrench -> 6 floats, ground_truth -> (p (N,3), R (N,3,3)),
    clock -> None. Identical numbers to rosbags' deserialize + the decode_* functions.
    """
    if len(data) < 12 or data[1] != 1:
        obj = deserialize(data, msgtype)
        if kind == "clock":
            return stamp_ns(obj.clock), None
        value = {
            "relative_pose": decode_relative_pose,
            "velocity": decode_twist,
            "wrench": decode_wrench,
            "ground_truth": decode_poses,
        }[kind](obj)
        return stamp_ns(obj.header.stamp), value
    if kind == "clock":
        return wire.stamp_of(data), None
    if kind == "relative_pose":
        stamp, values = _POSE_CODEC.decode(data)
        return stamp, wire.relative_pose_from_values(values)
    if kind in ("velocity", "wrench"):
        stamp, values = _SIX_CODEC.decode(data)
        return stamp, list(values)
    if kind == "ground_truth":
        stamp, p, R = wire.ground_truth_from_bytes(data)
        return stamp, (p, R)
    raise ValueError(f"no fast decoder for {kind!r}")


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
        self.Transform = t["geometry_msgs/msg/Transform"]
        self.TransformStamped = t[TRANSFORM_STAMPED]
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
        target: str,
        p: Sequence[float] | np.ndarray,
        R: Sequence[Sequence[float]] | np.ndarray,
    ) -> bytes:
        x, y, z, w = quaternion_from_matrix(R)
        msg = self.TransformStamped(
            header=self.header(ns, topics.agent_frame(observer)),
            child_frame_id=topics.agent_frame(target),
            transform=self.Transform(
                translation=self.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                rotation=self.Quaternion(x=x, y=y, z=z, w=w),
            ),
        )
        return bytes(self.ts.serialize_cdr(msg, TRANSFORM_STAMPED))

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
