"""CPU per display frame of the simulator: /formation/markers and /formation/funnels.

    .venv/bin/python benchmarks/display_bench.py [FORMATION ...]

"before": each Shape built as an rclpy Marker (display.marker_message), the MarkerArray serialized
by rclpy (what ``publish`` of a message object does); "after": the scene of the instant
(FormationScene.frame) written into the CDR templates of formation_sim.views.display_wire, funnels
included. CPU time (``time.process_time``) per frame, averaged; no DDS. Results in BENCHMARKS.md
("Realtime ROS 2 runs").
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from rclpy.serialization import serialize_message
from visualization_msgs.msg import MarkerArray

from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_msgs_py import topics
from formation_sim.core.simulation import Simulation
from formation_sim.node.display import FUNNEL_FIELDS, marker_message
from formation_sim.views.display_wire import FunnelsWire, MarkerArrayWire
from formation_sim.views.markers import FormationScene

REPO = Path(__file__).resolve().parents[1]
DEFAULT = ("paper_5agents.yaml", "realtime_20agents_100hz.yaml", "realtime_50agents_50hz.yaml")


def cpu_per_call(fn: Callable[[], object], repeat: int) -> float:
    """Mean CPU seconds of ``fn()`` over ``repeat`` calls, after one warm-up call."""
    fn()
    t0 = time.process_time()
    for _ in range(repeat):
        fn()
    return (time.process_time() - t0) / repeat


def frame_costs(path: Path) -> str:
    """One line: CPU per display frame before and after, at t = 0.7 s of the formation's start."""
    spec = load_formation(path)
    state = Simulation(simulator_view(spec)).state
    scene = FormationScene(spec)
    u = np.random.default_rng(0).normal(size=(len(spec.agents), 6))
    t, ns = 0.7, 700_000_000
    markers = MarkerArrayWire(scene, topics.WORLD_FRAME)
    funnels = FunnelsWire([e.name for e in spec.edges], FUNNEL_FIELDS)

    def before() -> None:
        shapes = scene.shapes(t, state.p, state.R, u)
        serialize_message(MarkerArray(markers=[marker_message(s, ns) for s in shapes]))

    def after() -> None:
        f = scene.frame(t, state.p, state.R, u)
        markers.encode(ns, f)
        funnels.encode(np.stack([f.funnels[name] for name in FUNNEL_FIELDS], axis=1))

    n_markers = len(scene.shapes(t, state.p, state.R, u))
    b, a = cpu_per_call(before, 20), cpu_per_call(after, 500)
    return (
        f"{path.name}: {len(spec.agents)} agents, {n_markers} markers: before {b * 1e3:.2f} ms, "
        f"after {a * 1e3:.3f} ms per frame ({b / a:.0f}x)"
    )


def main(argv: list[str]) -> int:
    for path in [Path(a) for a in argv] or [REPO / "config" / name for name in DEFAULT]:
        print(frame_costs(path), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
