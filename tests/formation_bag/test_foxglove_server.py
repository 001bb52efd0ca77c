"""The live view's server (formation_bag.foxglove_server), without ROS: endpoints, channels, bytes served."""

from __future__ import annotations

import socket
import subprocess
from collections import Counter

import numpy as np
import pytest
import websockets
from bin_helpers import executable
from live_client import receive
from mcap_ros2._dynamic import generate_dynamic

from formation_bag.foxglove_server import (
    DIAGNOSTIC_ARRAY,
    MARKER_ARRAY,
    SUBPROTOCOL,
    LiveView,
    LiveViewError,
    display_topics,
    endpoint_problem,
)
from formation_bag.writer import typestore
from formation_core.options import split_endpoint
from formation_core.so3 import exp_so3
from formation_core.spec import load_formation
from formation_msgs_py import topics
from formation_msgs_py.codec import clock_bytes
from formation_sim.views.display_wire import MarkerArrayWire
from formation_sim.views.markers import FormationScene

MARKERS = "/" + topics.MARKERS


@pytest.mark.parametrize(
    ("text", "expected"),
    [("8765", ("127.0.0.1", 8765)), ("0.0.0.0:0", ("0.0.0.0", 0)), ("[::1]:9000", ("::1", 9000))],
)
def test_endpoint_host_defaults_to_loopback(text: str, expected: tuple[str, int]) -> None:
    """[HOST:]PORT: the host is 127.0.0.1 unless given; an IPv6 host in brackets."""
    assert split_endpoint(text) == expected


@pytest.mark.parametrize(("text", "word"), [("x", "'x' is not an integer"), ("70000", "0..65535"), (":80", "empty")])
def test_endpoint_errors_name_the_value(text: str, word: str) -> None:
    """A bad endpoint is refused with a message naming it."""
    with pytest.raises(ValueError, match=word):
        split_endpoint(text)


def _scene_frame(spec, wire: MarkerArrayWire, scene: FormationScene, t: float, seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    n = len(spec.agents)
    p = rng.normal(scale=3.0, size=(n, 3))
    R = np.array([exp_so3(rng.normal(size=3)) for _ in range(n)])
    u = rng.normal(scale=20.0, size=(n, 6))
    return wire.encode(round(t * 1e9), scene.frame(t, p, R, u))


def test_markers_are_served_as_the_bytes_published(paper_path) -> None:
    """A client subscribed to the markers receives the published CDR bytes unchanged, on a `cdr` channel
    whose `ros2msg` schema decodes them (mcap_ros2, as a viewer) like rosbags does: a body per agent."""
    spec = load_formation(paper_path)
    scene = FormationScene(spec)
    wire = MarkerArrayWire(scene, topics.WORLD_FRAME)
    live = LiveView("127.0.0.1:0", name="test")
    sent: list[bytes] = []

    def tick() -> None:  # one display instant per call, 1/30 s of simulation time apart
        t = len(sent) / 30.0
        sent.append(_scene_frame(spec, wire, scene, t, seed=len(sent)))
        live.send(MARKERS, sent[-1], round(t * 1e9))
        live.send(topics.CLOCK, clock_bytes(round(t * 1e9)), round(t * 1e9))

    try:
        live.open(display_topics())
        got = receive(live.url, [MARKERS, topics.CLOCK], timeout=30.0, tick=tick)
    finally:
        live.close()
    channel = got.channels[MARKERS]
    assert (channel["encoding"], channel["schemaName"], channel["schemaEncoding"]) == ("cdr", MARKER_ARRAY, "ros2msg")
    assert got.channels[topics.DIAGNOSTICS]["schemaName"] == DIAGNOSTIC_ARRAY
    log_time, data = got.messages[MARKERS][0]
    index = round(log_time * 30.0 / 1e9)
    assert data == sent[index]
    msg = typestore().deserialize_cdr(data, MARKER_ARRAY)
    bodies = [m for m in msg.markers if m.ns == "bodies"]
    assert len(bodies) == len(spec.agents)
    assert Counter(m.ns for m in msg.markers) == Counter(s.ns for s in scene.shapes_of(scene.frame(0.0, *_zeros(spec))))
    decoded = generate_dynamic(MARKER_ARRAY, channel["schema"])[MARKER_ARRAY](data)
    assert [m.pose.position.x for m in decoded.markers] == [m.pose.position.x for m in msg.markers]
    clock_time, clock = got.messages[topics.CLOCK][0]
    assert typestore().deserialize_cdr(clock, "rosgraph_msgs/msg/Clock").clock.sec == clock_time // 1_000_000_000


def _zeros(spec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = len(spec.agents)
    return np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 6))


def test_only_the_sdk_subprotocol_is_accepted() -> None:
    """The server (foxglove-sdk 0.30) accepts foxglove.sdk.v1 and refuses foxglove.websocket.v1 (HTTP 400):
    the subprotocol docs/ros2.md names for viewers."""
    live = LiveView("127.0.0.1:0", name="test")
    try:
        live.open(display_topics())
        got = receive(live.url, [topics.CLOCK], timeout=30.0, tick=lambda: live.send(topics.CLOCK, clock_bytes(0), 0))
        assert set(got.channels) == set(display_topics())
        with pytest.raises(websockets.exceptions.InvalidStatus, match="400"):
            receive(live.url, [topics.CLOCK], subprotocol="foxglove.websocket.v1", timeout=30.0)
    finally:
        live.close()
    assert SUBPROTOCOL == "foxglove.sdk.v1"


def test_throttle_keeps_the_display_grid_and_every_diagnostics() -> None:
    """At 30 Hz, 100 messages 1 ms apart leave those at 0, 34 and 67 ms; /diagnostics is never throttled."""
    live = LiveView("127.0.0.1:0", name="test", rate=30.0)
    try:
        live.open(display_topics())
        kept = [k for k in range(100) if live.send(MARKERS, b"\0\1\0\0", k * 1_000_000)]
        assert kept == [0, 34, 67]
        assert sum(live.send(topics.DIAGNOSTICS, b"\0\1\0\0", k * 1_000_000) for k in range(100)) == 100
        live.rewind()  # a replay's next loop starts again at its first log time
        assert live.send(MARKERS, b"\0\1\0\0", 0)
    finally:
        live.close()


def test_a_port_in_use_is_refused_with_its_endpoint() -> None:
    """A taken port: LiveViewError naming the endpoint, no server left."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(LiveViewError, match=f"--foxglove 127.0.0.1:{port}: could not serve"):
            LiveView(f"127.0.0.1:{port}", name="test")


def test_launch_refuses_a_taken_port_before_starting_anything(paper_path, tmp_path) -> None:
    """formation-launch --foxglove on a port in use: exit 2, nothing started, the endpoint named."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert endpoint_problem(f"127.0.0.1:{port}") is not None
        launch = executable("formation-launch")
        cmd = [str(launch), str(paper_path), "--out", str(tmp_path / "out"), "--foxglove", str(port)]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stdout + res.stderr
    assert f"nothing started: --foxglove {port}: cannot listen on 127.0.0.1:{port}" in res.stderr
    assert not (tmp_path / "out" / "logs" / "sim.log").exists()
    assert endpoint_problem("127.0.0.1:0") is None
