"""Formation files: the paper preset loads; every class of bad file names its field."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from formation_core.errors import CollectedFormationSpecError, FormationSpecError
from formation_core.formation import agent_view, simulator_view
from formation_core.schema import AGENT_FIELDS, Parsed, UnusableValueError, block, parse_mapping, parse_partial
from formation_core.spec import formation_from_dict, load_formation

pytestmark = pytest.mark.numeric
# pytest.approx's default (relative 1e-6) checks a value against its closed form: rounding is some
# 1e-16 of it, a wrong formula or unit off by far more.


def test_paper_preset(paper_path: Path) -> None:
    """The paper preset: 5 agents, tree (1,2) (1,3) (3,4) (3,5), C_col = 2.25, C_con = 9.75."""
    spec = load_formation(paper_path)
    assert spec.agent_ids == ("1", "2", "3", "4", "5")
    assert [(e.tail, e.head) for e in spec.edges] == [("1", "2"), ("1", "3"), ("3", "4"), ("3", "5")]
    for e in spec.edges:
        assert (e.c_col, e.c_con) == pytest.approx((2.25, 9.75))
        assert e.rho_e(0.0) == pytest.approx(1.0)
        assert e.rho_e(1e9) == pytest.approx(0.1 / 9.75)
    assert spec.simulation.substeps == 1
    # projected rotations are exact rotations
    for R in [a.R_world_body for a in spec.agents] + [e.R_des for e in spec.edges]:
        # U·D·Vᵀ of an SVD (LAPACK: backward stable, orthogonal factors to a modest multiple of 3u; its
        # constants and summation order depend on the CPU's BLAS), then a 3-term product: ≤ 2e-14 = 90 ulp(1)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=2e-14)


def test_agent_view_holds_only_what_the_paper_lets_an_agent_know(paper_path: Path) -> None:
    """Agent 3's view: its gains and its three incident edges with roles; no plant."""
    spec = load_formation(paper_path)
    view = agent_view(spec, 3)
    assert view.neighbours == ("1", "4", "5")
    assert [ie.role for ie in view.edges] == ["head", "tail", "tail"]
    assert not hasattr(view, "dynamics") and not hasattr(view.controller, "mass")
    sim = simulator_view(spec)
    assert sim.agents[4].dynamics.mass == pytest.approx(0.053931)


def load(doc: dict[str, Any], tmp_path: Path):
    path = tmp_path / "f.yaml"
    path.write_text(yaml.safe_dump(doc))
    return load_formation(path)


def expect_error(doc: dict[str, Any], tmp_path: Path, field: str, text: str) -> FormationSpecError:
    with pytest.raises(FormationSpecError) as info:
        load(doc, tmp_path)
    assert info.value.path == field, str(info.value)
    assert text in str(info.value)
    # FILE:LINE:COL of the offending node, then the field
    assert re.match(rf"{re.escape(str(tmp_path / 'f.yaml'))}:\d+:\d+: {re.escape(field)}: ", str(info.value))
    return info.value


def test_not_a_tree(paper_doc, tmp_path) -> None:
    """A cycle is refused and names the edge that closes it."""
    paper_doc["edges"].append({"tail": 2, "head": 3})
    expect_error(paper_doc, tmp_path, "edges[4]", "closes a cycle")


def test_cycle_reduced_to_spanning_tree_on_request(paper_doc, tmp_path) -> None:
    """With spanning_tree: true the closing edge is dropped and reported."""
    paper_doc["edges"].append({"tail": 4, "head": 5})
    paper_doc["simulation"]["spanning_tree"] = True
    spec = load(paper_doc, tmp_path)
    assert len(spec.edges) == 4
    assert spec.dropped_edges == (("4", "5"),)


def test_disconnected(paper_doc, tmp_path) -> None:
    paper_doc["edges"].pop()
    err = expect_error(paper_doc, tmp_path, "edges", "disconnected")
    assert "{5}" in str(err)


def test_unknown_agent_in_edge(paper_doc, tmp_path) -> None:
    paper_doc["edges"][1]["head"] = 9
    expect_error(paper_doc, tmp_path, "edges[1].head", "unknown agent '9'")


def test_desired_distance_outside_bounds(paper_doc, tmp_path) -> None:
    """The message of the issue, to the letter."""
    paper_doc["edges"][2]["distance"] = 4.5
    err = expect_error(paper_doc, tmp_path, "edges[2].distance", "4.5 is not inside (d_col=2.0, d_con=4.0)")
    assert str(err).endswith(": edges[2].distance: 4.5 is not inside (d_col=2.0, d_con=4.0)")


def test_initial_distance_outside_bounds(paper_doc, tmp_path) -> None:
    paper_doc["agents"][1]["position"] = [0.0, 0.0, 1.5]
    expect_error(paper_doc, tmp_path, "edges[0]", "initial distance 1.5")


def test_psi0_above_rho_psi0(paper_doc, tmp_path) -> None:
    paper_doc["edges"][0]["orientation_funnel"] = {"rho_0": 1.5}
    expect_error(paper_doc, tmp_path, "edges[0].orientation_funnel.rho_0", "must exceed the initial orientation error")


def test_rho_psi0_not_below_two(paper_doc, tmp_path) -> None:
    paper_doc["edges"][0]["orientation_funnel"] = {"rho_0": 2.0}
    expect_error(paper_doc, tmp_path, "edges[0].orientation_funnel.rho_0", "must be below 2")


def test_matrix_not_a_rotation(paper_doc, tmp_path) -> None:
    """The paper's R_2(0) without project: true is an error that says how to fix it."""
    del paper_doc["agents"][1]["orientation"]["project"]
    expect_error(paper_doc, tmp_path, "agents[1].orientation.matrix", "is not a rotation")


def test_model_that_is_not_a_name(paper_doc, tmp_path) -> None:
    """A disturbance model given as a mapping is a field error, not a crash."""
    paper_doc["agents"][0]["dynamics"]["disturbance"] = {"model": {"paper": 1}}
    expect_error(paper_doc, tmp_path, "agents[0].dynamics.disturbance.model", "is not one of none, paper")


def test_non_positive_mass(paper_doc, tmp_path) -> None:
    paper_doc["agents"][0]["dynamics"]["mass"] = 0
    expect_error(paper_doc, tmp_path, "agents[0].dynamics.mass", "must be > 0")


def test_inertia_not_positive_definite(paper_doc, tmp_path) -> None:
    paper_doc["agents"][0]["dynamics"]["inertia"] = [0.1, -0.2, 0.3]
    expect_error(paper_doc, tmp_path, "agents[0].dynamics.inertia", "not positive definite")


def test_unknown_key(paper_doc, tmp_path) -> None:
    paper_doc["agents"][3]["colour"] = "red"
    expect_error(paper_doc, tmp_path, "agents[3].colour", "unknown key")
    paper_doc["agents"][3].pop("colour")
    paper_doc["simulation"]["rate"] = 5
    expect_error(paper_doc, tmp_path, "simulation.rate", "unknown key")


def test_wrong_types(paper_doc, tmp_path) -> None:
    paper_doc["agents"][2]["position"] = [1.3, "a", 1.5]
    expect_error(paper_doc, tmp_path, "agents[2].position[1]", "expected a number, got str 'a'")
    paper_doc["agents"][2]["position"] = [1.3, 1.3, 1.5]
    paper_doc["simulation"]["seed"] = 1.5
    expect_error(paper_doc, tmp_path, "simulation.seed", "expected an integer")
    paper_doc["simulation"]["seed"] = 0
    paper_doc["simulation"]["mode"] = "fast"
    expect_error(paper_doc, tmp_path, "simulation.mode", "'fast' is not one of lockstep, realtime")


def test_physics_rate_multiple_of_control_rate(paper_doc, tmp_path) -> None:
    paper_doc["simulation"]["physics_rate"] = 15000.0
    expect_error(paper_doc, tmp_path, "simulation.physics_rate", "not an integer multiple of control_rate")


def test_duplicate_agent_id(paper_doc, tmp_path) -> None:
    paper_doc["agents"][4]["id"] = 1
    expect_error(paper_doc, tmp_path, "agents[4].id", "is used by agents[0] too")


def test_rotation_forms_agree() -> None:
    """matrix, quaternion (x, y, z, w), rpy and axis-angle give the same rotation."""
    forms = [
        {"matrix": [[0, -1, 0], [1, 0, 0], [0, 0, 1]]},
        {"quaternion": [0, 0, 0.7071067811865476, 0.7071067811865476]},
        {"rpy": [0, 0, 1.5707963267948966]},
        {"axis_angle": {"axis": [0, 0, 3], "angle": 1.5707963267948966}},
    ]
    mats = []
    for form in forms:
        doc = minimal_doc()
        doc["agents"][1]["orientation"] = form
        mats.append(formation_from_dict(doc).agents[1].R_world_body)
    for R in mats[1:]:
        # each form through its own trigonometry or square root, then the SVD projection (as above): ≤ 90 ulp(1)
        np.testing.assert_allclose(R, mats[0], atol=2e-14)


def test_missing_file_and_bad_yaml(tmp_path) -> None:
    with pytest.raises(FormationSpecError, match="does not exist"):
        load_formation(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("agents: [\n")
    with pytest.raises(FormationSpecError, match=r"bad.yaml:2:1: not valid YAML: .*node content"):
        load_formation(bad)


def minimal_doc() -> dict[str, Any]:
    agent = {"radius": 0.5, "sensing_radius": 3.0, "dynamics": {"mass": 1.0, "inertia": [0.1, 0.1, 0.1]}}
    return {
        "agents": [{"id": "a", "position": [0, 0, 0], **agent}, {"id": "b", "position": [2, 0, 0], **agent}],
        "edges": [{"tail": "a", "head": "b", "distance": 1.5}],
    }


def test_defaults_fill_a_minimal_file() -> None:
    """Defaults: d_col = r_t + r_h, d_con = min(s), identity rotations, paper gains."""
    spec = formation_from_dict(minimal_doc())
    e = spec.edges[0]
    assert (e.d_col, e.d_con) == (1.0, 3.0)
    np.testing.assert_array_equal(e.R_des, np.eye(3))
    assert spec.agents[0].controller.gamma == 15.0
    assert spec.agents[0].controller.velocity_funnel.rho_0 is None  # auto


def error_paths(doc: dict[str, Any]) -> list[str]:
    """The field path of every error formation_from_dict reports for ``doc``, in the order found."""
    with pytest.raises(FormationSpecError) as info:
        formation_from_dict(doc)
    return [e.path for e in getattr(info.value, "errors", [info.value])]


def test_semantic_checks_run_beside_field_errors() -> None:
    """An unknown key and a wrong type do not hide a reflection or a distance outside its bounds."""
    doc = minimal_doc()
    doc["agents"][0]["controller"] = {"gama": 3.0}
    doc["agents"][0]["dynamics"] = {"mass": "heavy", "inertia": [0.1, 0.1, 0.1]}
    doc["agents"][1]["orientation"] = {"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}
    doc["edges"][0]["distance"] = 3.0
    assert error_paths(doc) == [
        "agents[0].controller.gama",
        "agents[0].dynamics.mass",
        "agents[1].orientation.matrix",
        "edges[0].distance",
    ]


def test_every_semantic_check_of_an_edge_runs() -> None:
    """Three broken constraints of one edge: three errors, not the first only."""
    doc = minimal_doc()
    doc["edges"][0].update(distance=3.0, orientation_funnel={"rho_0": 2.0, "rho_inf": 2.5})
    assert error_paths(doc) == [
        "edges[0].distance",
        "edges[0].orientation_funnel.rho_0",
        "edges[0].orientation_funnel.rho_inf",
    ]


def test_a_check_that_needs_a_broken_value_is_skipped() -> None:
    """Agent b's position is unusable: the initial distance of its edge is not checked (no invented
    error), the edge's other checks run."""
    doc = minimal_doc()
    doc["agents"][1]["position"] = [2, 0]
    doc["edges"][0]["distance"] = 3.0
    assert error_paths(doc) == ["agents[1].position", "edges[0].distance"]


def test_an_agent_without_a_usable_id_hides_no_edge_error() -> None:
    """Agent b's id is a list: no edge is called unknown or the graph disconnected, yet the edge's own
    checks that need no agent still run."""
    doc = minimal_doc()
    doc["agents"][1]["id"] = ["b"]
    doc["edges"][0]["orientation_funnel"] = {"rho_0": 2.0}
    assert error_paths(doc) == ["agents[1].id", "edges[0].orientation_funnel.rho_0"]


def test_every_cycle_is_reported(paper_doc) -> None:
    """Two edges that each close a cycle: both named; their own checks are skipped (each must go)."""
    paper_doc["edges"] += [{"tail": 2, "head": 3}, {"tail": 4, "head": 5}]
    assert error_paths(paper_doc) == ["edges[4]", "edges[5]"]


def test_parse_partial_keeps_what_parsed() -> None:
    """A bad field and an unknown key in the controller: every error, and the other fields' values;
    reading the bad one raises UnusableValueError."""
    fields = block(AGENT_FIELDS, "controller")
    values, errors = parse_partial({"gamma": "x", "gama": 3.0, "delta": 0.2}, fields, "agents[0].controller")
    assert [e.path for e in errors] == ["agents[0].controller.gama", "agents[0].controller.gamma"]
    assert isinstance(values, Parsed) and values["delta"] == 0.2
    assert values["velocity_funnel"]["rho_inf"] == (0.1,) * 6  # a nested map parsed field by field
    with pytest.raises(UnusableValueError):
        values["gamma"]
    with pytest.raises(CollectedFormationSpecError):  # parse_mapping: the same errors, raised
        parse_mapping({"gamma": "x", "gama": 3.0}, fields, "agents[0].controller")
