"""The viewer's scene of a formation, without ROS: bodies, frames, margin colours, ghosts, arrows."""

from __future__ import annotations

import numpy as np
import pytest

from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_sim.core.simulation import Simulation
from formation_sim.views.markers import ARROW, SPHERE, FormationScene, arrow_length, margin_colour

pytestmark = pytest.mark.numeric


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
    """One body, frame, label, two arrows and a contact sphere (clear: nothing touches) per agent; one line
    and one ghost per edge; values at t=0."""
    scene, spec, state = scene_and_state
    u = np.tile([3.0, 0.0, 0.0, 0.0, 0.0, 0.0], (len(spec.agents), 1))
    shapes = scene.shapes(0.0, state.p, state.R, u)
    count: dict[str, int] = {}
    for s in shapes:
        count[s.ns] = count.get(s.ns, 0) + 1
    assert count == {
        "bodies": 5, "frames": 5, "labels": 5, "forces": 5, "torques": 5, "edges": 4, "desired": 4, "contacts": 5
    }  # fmt: skip
    assert all(s.color[3] == 0.0 for s in shapes if s.ns == "contacts")
    frames = {s.id: s for s in shapes if s.ns == "frames"}
    i = 1  # agent 2: its frame's x axis is the first column of R_world_body, r_i long
    # marker geometry: a few roundings of positions and lengths of a few metres (ulp(8) = 1.8e-15) below
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
    from formation_sim.core.judge import EdgeErrors

    scene, spec, state = scene_and_state
    f = scene.funnels(0.7, state.p, state.R)
    ref = EdgeErrors(spec)
    e, psi = ref.errors(state.p, state.R)
    rho_e, rho_psi = ref.rho(0.7)
    # the same code on the same inputs: the same bits
    np.testing.assert_array_equal(f["e"], e)
    np.testing.assert_array_equal(f["psi"], psi)
    np.testing.assert_array_equal(f["e_upper"], ref.c_con * rho_e)
    np.testing.assert_array_equal(f["rho_psi"], rho_psi)
    start = scene.funnels(0.0, state.p, state.R)  # the paper starts inside every funnel
    assert np.all(start["margin_e"] > 0) and np.all(start["margin_psi"] > 0)
    assert np.any(f["margin_e"] < 0)  # the initial poses held still until 0.7 s leave a distance funnel


def test_foxglove_layout_reads_the_display_topics(paper_path) -> None:
    """foxglove/formation_layout.json is the paper's generated layout: a 3D view of the markers; every edge's
    e and ψ once; one bound pair for the four edges' identical funnels; named lines, no values in legends."""
    import json
    import re

    from formation_msgs_py import topics
    from formation_sim.views.foxglove_layout import layout_text

    spec = load_formation(paper_path)
    shipped = (paper_path.parents[1] / "foxglove" / "formation_layout.json").read_text(encoding="utf-8")
    assert shipped == layout_text(spec), "regenerate: formation_sim.views.foxglove_layout.layout_text"
    panels = json.loads(shipped)["configById"]
    assert panels["3D!formation"]["topics"]["/" + topics.MARKERS]["visible"] is True
    plots = [cfg for cfg in panels.values() if "paths" in cfg]
    assert all(cfg["showPlotValuesInLegend"] is False for cfg in plots)
    lines = {
        re.fullmatch(r"/formation/funnels\.data\[(\d+)\]", p["value"])[1]: p["label"] for c in plots for p in c["paths"]
    }
    k = len(spec.edges)
    assert "/" + topics.FUNNELS == "/formation/funnels"
    assert {int(i) for i in lines} == {*(5 * j for j in range(k)), *(5 * j + 3 for j in range(k)), 1, 2, 4}
    assert lines["0"] == "e 1-2" and lines["3"] == "ψ 1-2"
    assert lines["2"] == "C_con·ρ_e (1-2, 1-3, 3-4, 3-5)"


def test_foxglove_layout_gives_each_distinct_funnel_its_bounds(paper_path) -> None:
    """An edge whose distance funnel differs from the others' gets a bound pair of its own."""
    from dataclasses import replace

    from formation_sim.views.foxglove_layout import foxglove_layout

    spec = load_formation(paper_path)
    spec = replace(spec, edges=(replace(spec.edges[0], rho_e_inf=0.5 * spec.edges[0].rho_e_inf), *spec.edges[1:]))
    labels = [p["label"] for p in foxglove_layout(spec)["configById"]["Plot!distance"]["paths"]]
    assert [x for x in labels if x.startswith("C_con")] == ["C_con·ρ_e (1-2)", "C_con·ρ_e (1-3, 3-4, 3-5)"]
    psi = [p["label"] for p in foxglove_layout(spec)["configById"]["Plot!orientation"]["paths"]]
    assert [x for x in psi if x.startswith("ρ_ψ")] == ["ρ_ψ (1-2, 1-3, 3-4, 3-5)"]


def test_two_bodies_in_contact_are_drawn_as_such(scene_and_state) -> None:
    """Agents 2 and 4 (no edge between them) moved onto each other: their contact spheres turn red, the
    others' stay clear."""
    scene, _, state = scene_and_state
    p = state.p.copy()
    p[3] = p[1] + [0.5, 0.0, 0.0]  # 0.5 m apart, radii 1 m each: overlapping
    contacts = {s.id: s for s in scene.shapes(0.0, p, state.R, None) if s.ns == "contacts"}
    assert [i for i, s in sorted(contacts.items()) if s.color[3] > 0] == [1, 3]
    assert contacts[3].position == tuple(p[3].tolist()) and contacts[3].scale == (2.0, 2.0, 2.0)
