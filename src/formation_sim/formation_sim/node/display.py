"""The simulator's display topics: markers, funnel values and (where installed) TF.

At ``marker_rate`` Hz of simulation time (default 30; 0 turns it off) the simulator publishes

- ``/formation/markers`` (visualization_msgs/MarkerArray, frame ``world``): the scene of
  :mod:`formation_sim.views.markers`;
- ``/formation/funnels`` (std_msgs/Float64MultiArray): per edge k, in file order, the five values
  ``e_k, −C_col·ρ_e, C_con·ρ_e, ψ_k, ρ_ψ`` at ``data[5k … 5k+4]`` (for plots: Foxglove, PlotJuggler);
- ``/tf`` (tf2_msgs/TFMessage) ``world → agent_<id>``, only where tf2_msgs is importable: an apt
  install of ROS 2 has it, the PyPI wheels of ``ros2_ws/requirements.txt`` do not.

With ``--foxglove`` the same bytes of markers and funnels, ``/clock`` at each display instant and
every ``/diagnostics`` received are served to the live view too (:mod:`formation_bag.foxglove_server`).

Nothing here is read by an agent (docs/topics.md).
"""

from __future__ import annotations

import importlib
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point, TransformStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from std_msgs.msg import ColorRGBA, Float64MultiArray
from visualization_msgs.msg import Marker, MarkerArray

from formation_bag.foxglove_server import LiveView, display_topics
from formation_core.formation import FormationSpec, simulator_view
from formation_core.options import RunOptions
from formation_msgs_py import topics
from formation_msgs_py.codec import clock_bytes
from formation_msgs_py.ros import conversions, qos
from formation_ros import parameters
from formation_sim.core.links import CHANNELS, link_names
from formation_sim.views.display_wire import FUNNEL_FIELDS, FunnelsWire, MarkerArrayWire
from formation_sim.views.markers import FormationScene, Shape

DEFAULT_MARKER_RATE = 30.0


def _tf_message_class() -> type | None:
    """tf2_msgs/TFMessage where installed (apt), else None (the PyPI wheels have no tf2_msgs)."""
    try:
        return importlib.import_module("tf2_msgs.msg").TFMessage
    except ImportError:
        return None


def marker_message(shape: Shape, ns: int, frame: str = topics.WORLD_FRAME) -> Marker:
    """One Shape as an rclpy Marker, field by field, stamped ``ns`` [integer ns]: what the simulator
    published before display_wire (~0.13 ms per marker with its serialization); the reference
    tests/ros/test_display_wire.py and benchmarks/display_bench.py compare the template with."""
    m = Marker()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(ns, conversions.NS_PER_S)
    m.header.frame_id = frame
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


class DisplayPublisher:
    """Publishes the display topics of ``spec`` on ``node`` every 1/``rate`` s of simulation time
    (and serves them to ``live``, if given)."""

    def __init__(
        self, node: Node, spec: FormationSpec, rate: float = DEFAULT_MARKER_RATE, live: LiveView | None = None
    ) -> None:
        self.scene = FormationScene(spec)
        # both topics are written as CDR bytes into a template (display_wire: ~0.4 ms per frame for
        # 20 agents instead of ~20 ms as rclpy messages)
        self.markers = MarkerArrayWire(self.scene, topics.WORLD_FRAME)
        self.funnels = FunnelsWire([e.name for e in spec.edges], FUNNEL_FIELDS)
        self.frames = [topics.agent_frame(a) for a in spec.agent_ids]
        self.markers_pub = node.create_publisher(MarkerArray, topics.MARKERS, qos.DISPLAY)
        self.funnels_pub = node.create_publisher(Float64MultiArray, topics.FUNNELS, qos.DISPLAY)
        # with a link model: every link's age, rows "channel:link" (formation_sim.core.links.link_names)
        self.links_wire: FunnelsWire | None = None
        self.links_pub: Any = None
        if spec.has_links:
            names = link_names(simulator_view(spec))
            labels = [f"{channel}:{name}" for channel in CHANNELS for name in names[channel]]
            self.links_wire = FunnelsWire(labels, ("age",), rows="link")
            self.links_pub = node.create_publisher(Float64MultiArray, topics.LINKS, qos.DISPLAY)
        tf_class = _tf_message_class()
        self.tf_class = tf_class
        self.tf_pub = None if tf_class is None else node.create_publisher(tf_class, topics.TF, qos.DISPLAY)
        self.rate = 0.0
        self.next_t = 0.0
        self.set_rate(rate)
        self.live = live
        self.last_ns = 0  # of the last display instant: the live view's log time of /diagnostics
        if live is not None:
            links = None if self.links_pub is None else self.links_pub.topic_name
            live.open(display_topics(self.markers_pub.topic_name, self.funnels_pub.topic_name, links))
            self.diagnostics_sub = node.create_subscription(
                DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, qos.DIAGNOSTICS, raw=True
            )

    def _on_diagnostics(self, data: bytes) -> None:
        self.live.send(topics.DIAGNOSTICS, data, self.last_ns)  # type: ignore[union-attr]  # only with live

    def set_rate(self, rate: float) -> None:
        """Display rate [Hz, simulation time]; 0 stops publishing."""
        self.rate = float(rate)

    def due(self, t: float) -> bool:
        return self.rate > 0.0 and t >= self.next_t - 1e-12

    def publish_link_ages(self, t: float, ages: np.ndarray) -> None:
        """``/formation/links``: every link's held sample's age [s] (NaN: none yet) at simulation time t [s],
        a display instant (:meth:`due`)."""
        if self.links_wire is None or self.links_pub is None:
            return
        data = self.links_wire.encode(ages[:, None])
        self.links_pub.publish(data)
        if self.live is not None:
            self.live.send(self.links_pub.topic_name, data, round(t * conversions.NS_PER_S))

    def publish(self, t: float, p: np.ndarray, R: np.ndarray, u: np.ndarray | None) -> None:
        """Publish the scene at simulation time t [s] if a display instant is due."""
        if not self.due(t):
            return
        self.next_t = (np.floor(t * self.rate + 1e-6) + 1.0) / self.rate  # on the grid k/rate: no drift
        ns = round(t * conversions.NS_PER_S)
        f = self.scene.frame(t, p, R, u)
        markers = self.markers.encode(ns, f)
        self.markers_pub.publish(markers)
        funnels = self.funnels.encode(np.stack([f.funnels[name] for name in FUNNEL_FIELDS], axis=1))
        self.funnels_pub.publish(funnels)
        if self.live is not None:  # the bytes just published: the live view costs a step its sends only
            self.last_ns = ns
            self.live.send(self.markers_pub.topic_name, markers, ns)
            self.live.send(self.funnels_pub.topic_name, funnels, ns)
            self.live.send(topics.CLOCK, clock_bytes(ns), ns)
        if self.tf_pub is not None and self.tf_class is not None:
            stamp = conversions.stamp_from_seconds(t)
            frame = topics.WORLD_FRAME
            transforms = []
            for i, child in enumerate(self.frames):
                tf = TransformStamped()
                tf.header.stamp = stamp
                tf.header.frame_id = frame
                tf.child_frame_id = child
                tr = tf.transform.translation
                tr.x, tr.y, tr.z = (float(x) for x in p[i])
                q = tf.transform.rotation
                q.x, q.y, q.z, q.w = f.q[i].tolist()
                transforms.append(tf)
            self.tf_pub.publish(self.tf_class(transforms=transforms))


def declare_simulator_parameters(
    node: Node, spec: FormationSpec, args: RunOptions, live: LiveView | None = None
) -> DisplayPublisher:
    """The simulator's parameters and its display publisher.

    The settings of :data:`SETTING_DOCS` are declared read-only: they show what the command line
    (``args``, after preflight) chose and cannot change a running simulation. ``marker_rate`` is live.
    """
    settings = {
        "formation_file": str(args.file),
        "mode": args.mode,
        "control_rate": spec.simulation.control_rate,
        "measurement_qos": args.measurement_qos,
    }
    for name, doc in SETTING_DOCS.items():
        parameters.declare(node, name, settings[name], doc, read_only=True)
    rate = parameters.declare(node, "marker_rate", float(args.marker_rate), MARKER_RATE_DOC, low=0.0, high=1000.0)
    display = DisplayPublisher(node, spec, rate, live)

    def on_set(params: list) -> SetParametersResult:
        for prm in params:
            if prm.name == "marker_rate":
                display.set_rate(prm.value)
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)
    return display


MARKER_RATE_DOC = "display rate [Hz of simulation time] of /formation/markers, /formation/funnels and /tf; 0: off; live"
SETTING_DOCS = {
    "formation_file": "formation file (YAML), from the command line",
    "mode": "lockstep or realtime (--mode)",
    "control_rate": "control rate [Hz] (--control-rate or simulation.control_rate)",
    "measurement_qos": "reliable or best-effort (--measurement-qos)",
}
