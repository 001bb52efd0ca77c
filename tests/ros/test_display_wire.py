"""The display topics' CDR templates (formation_sim.views.display_wire) read back as rclpy's messages."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from visualization_msgs.msg import MarkerArray

from formation_core.so3 import exp_so3
from formation_core.spec import load_formation
from formation_msgs_py import topics
from formation_msgs_py.ros import conversions
from formation_sim.node.display import FUNNEL_FIELDS, marker_message
from formation_sim.views.display_wire import FunnelsWire, MarkerArrayWire
from formation_sim.views.markers import FormationScene


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
        expected = MarkerArray(markers=[marker_message(s, ns) for s in scene.shapes(t, p, R, u)])
        reference = serialize_message(expected)
        got = deserialize_message(data, MarkerArray)
        assert len(got.markers) == 6 * n + 2 * len(spec.edges)  # a contact sphere per agent too
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
