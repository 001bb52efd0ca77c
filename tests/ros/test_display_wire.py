"""The display topics' CDR templates (formation_sim.display_wire) read back as rclpy's messages."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import Point
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import ColorRGBA, Float64MultiArray, MultiArrayDimension
from visualization_msgs.msg import Marker, MarkerArray

from formation_msgs_py import conversions, topics
from formation_msgs_py.so3 import exp_so3
from formation_msgs_py.spec import load_formation
from formation_sim.display import FUNNEL_FIELDS
from formation_sim.display_wire import FunnelsWire, MarkerArrayWire
from formation_sim.markers import FormationScene, Shape


def as_message(shape: Shape, ns: int) -> Marker:
    """The Marker of a Shape, built field by field as rclpy messages (the reference)."""
    m = Marker()
    sec, nsec = divmod(ns, conversions.NS_PER_S)
    m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
    m.header.frame_id = topics.WORLD_FRAME
    m.ns, m.id, m.type, m.action = shape.ns, shape.id, shape.type, Marker.ADD
    m.pose.position.x, m.pose.position.y, m.pose.position.z = shape.position
    o = m.pose.orientation
    o.x, o.y, o.z, o.w = shape.orientation
    m.scale.x, m.scale.y, m.scale.z = shape.scale
    m.color = ColorRGBA(r=shape.color[0], g=shape.color[1], b=shape.color[2], a=shape.color[3])
    m.points = [Point(x=x, y=y, z=z) for x, y, z in shape.points]
    m.colors = [ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b, a in shape.colors]
    m.text = shape.text
    return m


@pytest.mark.parametrize("name", ["paper_5agents.yaml", "realtime_20agents_100hz.yaml"])
def test_markers_read_back_as_the_scene(paper_path, name) -> None:
    """Three frames of random poses and wrenches: rclpy reads every marker of the scene, exactly."""
    spec = load_formation(paper_path.with_name(name))
    scene = FormationScene(spec)
    wire = MarkerArrayWire(scene, topics.WORLD_FRAME)
    rng = np.random.default_rng(7)
    n = len(spec.agents)
    for t in (0.0, 0.7, 123.456789):
        p = rng.normal(scale=3.0, size=(n, 3))
        R = np.array([exp_so3(rng.normal(size=3)) for _ in range(n)])
        u = rng.normal(scale=20.0, size=(n, 6))
        u[0] = 0.0  # no arrow length for a zero wrench
        ns = round(t * conversions.NS_PER_S)
        data = wire.encode(ns, scene.frame(t, p, R, u))
        expected = MarkerArray(markers=[as_message(s, ns) for s in scene.shapes(t, p, R, u)])
        reference = serialize_message(expected)
        got = deserialize_message(data, MarkerArray)
        assert len(got.markers) == 5 * n + 2 * len(spec.edges)
        assert got == deserialize_message(reference, MarkerArray)  # colours as float32, as sent
        assert len(data) == len(reference)  # the same layout (padding bytes are unspecified)


def test_funnels_read_back_with_their_layout(paper_path) -> None:
    spec = load_formation(paper_path)
    names = [e.name for e in spec.edges]
    wire = FunnelsWire(names, FUNNEL_FIELDS)
    values = np.random.default_rng(3).normal(size=(len(names), len(FUNNEL_FIELDS)))
    got = deserialize_message(wire.encode(values), Float64MultiArray)
    k = len(names)
    expected = Float64MultiArray(data=values.ravel().tolist())
    expected.layout.dim = [
        MultiArrayDimension(label="edge " + ",".join(names), size=k, stride=5 * k),
        MultiArrayDimension(label=",".join(FUNNEL_FIELDS), size=5, stride=5),
    ]
    assert got == expected
