"""The viewer's scene of a formation, without ROS: bodies, frames, margin colours, ghosts, arrows."""

from __future__ import annotations

import numpy as np
import pytest

from formation_msgs_py.spec import load_formation, simulator_view
from formation_sim.core.simulation import Simulation
from formation_sim.views.markers import ARROW, SPHERE, FormationScene, arrow_length, margin_colour


@pytest.fixture
def scene_and_state(paper_path):
    spec = load_formation(paper_path)
    state = Simulation(simulator_view(spec)).state
    return FormationScene(spec), spec, state


def test_margin_colours() -> None:
    """Green at the centre, yellow half-way, red on the bound, magenta outside or NaN."""
    assert margin_colour(1.0) == (0.0, 0.8, 0.0, 1.0)
    assert margin_colour(0.5) == (1.0, 0.8, 0.0, 1.0)
    assert margin_colour(0.0) == (1.0, 0.0, 0.0, 1.0)
    assert margin_colour(-0.1) == margin_colour(float("nan")) == (1.0, 0.0, 1.0, 1.0)


def test_scene_of_the_paper_start(scene_and_state) -> None:
    """One body, frame, label and two arrows per agent; one line and one ghost per edge; values at t=0."""
    scene, spec, state = scene_and_state
    u = np.tile([3.0, 0.0, 0.0, 0.0, 0.0, 0.0], (len(spec.agents), 1))
    shapes = scene.shapes(0.0, state.p, state.R, u)
    count: dict[str, int] = {}
    for s in shapes:
        count[s.ns] = count.get(s.ns, 0) + 1
    assert count == {"bodies": 5, "frames": 5, "labels": 5, "forces": 5, "torques": 5, "edges": 4, "desired": 4}
    frames = {s.id: s for s in shapes if s.ns == "frames"}
    i = 1  # agent 2: its frame's x axis is the first column of R_world_body, r_i long
    np.testing.assert_allclose(np.subtract(frames[i].points[1], frames[i].points[0]), state.R[i][:, 0], atol=1e-12)
    k = 0  # edge 1-2: the ghost sits d_des from the tail towards the head
    ghost = next(s for s in shapes if s.ns == "desired" and s.id == k)
    assert ghost.type == SPHERE
    tail, head = state.p[0], state.p[1]
    expected = tail + (head - tail) / np.linalg.norm(head - tail) * spec.edges[k].d_des
    np.testing.assert_allclose(ghost.position, expected, atol=1e-12)
    force = next(s for s in shapes if s.ns == "forces" and s.id == i)
    assert force.type == ARROW
    vector = np.subtract(force.points[1], force.points[0])
    # 3 N along body x: along R's first column, length 0.25·r·ln(1 + 3)
    np.testing.assert_allclose(vector, state.R[i][:, 0] * arrow_length(3.0, 0.25 * spec.agents[i].radius), atol=1e-12)


def test_funnel_values_match_the_report(scene_and_state) -> None:
    """e, ψ and their bounds equal the run recorder's (one definition of the funnels)."""
    from formation_msgs_py.judge import EdgeErrors

    scene, spec, state = scene_and_state
    f = scene.funnels(0.7, state.p, state.R)
    ref = EdgeErrors(spec)
    e, psi = ref.errors(state.p, state.R)
    rho_e, rho_psi = ref.rho(0.7)
    np.testing.assert_allclose(f["e"], e, rtol=1e-12)
    np.testing.assert_allclose(f["psi"], psi, rtol=1e-12)
    np.testing.assert_allclose(f["e_upper"], ref.c_con * rho_e, rtol=1e-12)
    np.testing.assert_allclose(f["rho_psi"], rho_psi, rtol=1e-12)
    start = scene.funnels(0.0, state.p, state.R)  # the paper starts inside every funnel
    assert np.all(start["margin_e"] > 0) and np.all(start["margin_psi"] > 0)
    assert np.any(f["margin_e"] < 0)  # the initial poses held still until 0.7 s leave a distance funnel


def test_foxglove_layout_reads_the_display_topics(paper_path) -> None:
    """foxglove/formation_layout.json: a 3D view of the markers; plots of every paper edge's e, ψ and bounds."""
    import json
    import re

    from formation_msgs_py import topics

    layout = json.loads((paper_path.parents[1] / "foxglove" / "formation_layout.json").read_text())
    panels = layout["configById"]
    assert panels["3D!formation"]["topics"]["/" + topics.MARKERS]["visible"] is True
    paths = [p["value"] for cfg in panels.values() for p in cfg.get("paths", [])]
    indices = sorted(int(re.fullmatch(r"/formation/funnels\.data\[(\d+)\]", v)[1]) for v in paths)
    assert "/" + topics.FUNNELS == "/formation/funnels"
    edges = len(load_formation(paper_path).edges)
    assert indices == list(range(5 * edges))  # e, −C_col·ρ_e, C_con·ρ_e, ψ, ρ_ψ of every edge, once
