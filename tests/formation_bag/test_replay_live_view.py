"""formation-replay --foxglove: the replayed display topics reach a Foxglove WebSocket client as recorded."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
from bag_helpers import PAPER, script
from live_client import wait_and_receive

from formation_bag import messages as m
from formation_bag.writer import SegmentedBagWriter
from formation_core.so3 import exp_so3
from formation_core.spec import load_formation
from formation_msgs_py import topics
from formation_sim.views.display_wire import MarkerArrayWire
from formation_sim.views.markers import FormationScene

MARKERS = "/" + topics.MARKERS


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_replay_serves_the_recorded_markers_and_clock(ros_procs, tmp_path: Path) -> None:
    """A bag with markers at 30 Hz and /clock at 1 kHz, replayed in a loop with --foxglove: the client
    gets markers byte for byte as recorded and /clock; only the display topics the bag has are advertised."""
    spec = load_formation(PAPER)
    scene = FormationScene(spec)
    wire = MarkerArrayWire(scene, topics.WORLD_FRAME)
    rng = np.random.default_rng(11)
    n = len(spec.agents)
    start = 1_700_000_000 * m.NS_PER_S
    enc = m.Encoder()
    recorded = set()
    bag = tmp_path / "bag"
    with SegmentedBagWriter(bag) as w:
        w.add_topic(topics.CLOCK, m.CLOCK)
        w.add_topic(MARKERS, m.MARKER_ARRAY)
        for k in range(500):  # 0.5 s of bag time
            t_ns = k * 1_000_000
            w.write(topics.CLOCK, start + t_ns, enc.clock(t_ns))
            if k % 33 == 0:
                p = rng.normal(scale=3.0, size=(n, 3))
                R = np.array([exp_so3(rng.normal(size=3)) for _ in range(n)])
                data = wire.encode(t_ns, scene.frame(t_ns / 1e9, p, R, rng.normal(size=(n, 6))))
                recorded.add(data)
                w.write(MARKERS, start + t_ns, data)
    port = _free_port()
    rep = ros_procs.start(
        [*script("formation-replay"), str(bag), "--loop", "--wait", "none", "--quiet", "--foxglove", str(port)]
    )
    ros_procs.wait_line(rep, f"live view on ws://127.0.0.1:{port}", 60)
    got = wait_and_receive(
        f"ws://127.0.0.1:{port}", [MARKERS, topics.CLOCK], alive=lambda: rep.poll() is None, timeout=120
    )
    assert set(got.channels) == {MARKERS, topics.CLOCK}
    assert got.messages[MARKERS][0][1] in recorded
    log_time, clock = got.messages[topics.CLOCK][0]
    assert log_time >= start and clock == enc.clock(log_time - start)
