"""The formation-file reference in docs/ is generated from the schema and kept in step."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import yaml

from formation_core import formation, spec
from formation_core.schema import (
    AGENT_FIELDS,
    EDGE_FIELDS,
    SIMULATION_FIELDS,
    attribute_type,
    attributes,
    block,
    schema_markdown,
)

REPO = Path(__file__).resolve().parents[2]


def test_docs_reference_matches_schema() -> None:
    """docs/formation_file.md holds the table `formation-check --schema` prints, verbatim."""
    doc = (REPO / "docs" / "formation_file.md").read_text(encoding="utf-8")
    assert schema_markdown() in doc, "regenerate: formation-check --schema (see docs/formation_file.md)"


_BUILT = [
    (formation.SimulationSpec, SIMULATION_FIELDS, ()),
    (formation.ControllerGains, block(AGENT_FIELDS, "controller"), ()),
    (formation.VelocityFunnel, block(AGENT_FIELDS, "controller", "velocity_funnel"), ()),
    (formation.Dynamics, block(AGENT_FIELDS, "dynamics"), ()),
    (formation.AgentSpec, AGENT_FIELDS, ("index",)),
    (formation.EdgeSpec, EDGE_FIELDS, ("index",)),
]


def test_built_records_have_exactly_the_declared_fields() -> None:
    """One declaration: every object a block builds has the schema's fields as attributes, in order
    (an ``attr`` renames, an ``inline`` map's fields belong to the agent or edge; ``index`` is derived)."""
    for cls, fields, derived in _BUILT:
        names = [f.attr or f.name for _, f in attributes(fields)]
        assert [f.name for f in dataclasses.fields(cls)] == [*derived, *names], cls
        assert cls.__module__ == "formation_core.formation" and "Attributes" in (cls.__doc__ or "")
    assert [f.name for f in dataclasses.fields(formation.EdgeSpec)][3:5] == ["d_des", "R_des"]


def test_built_records_have_the_declared_types_and_no_defaults() -> None:
    """Each written attribute's annotation is the schema's type of its field (the kind's, or the field's
    own where the loader converts further); no attribute has a default, so the schema's are the only ones."""
    for cls, fields, derived in _BUILT:
        hints = typing.get_type_hints(cls, vars(spec))
        expected = {name: int for name in derived}
        expected.update({f.attr or f.name: eval(attribute_type(f), vars(spec)) for _, f in attributes(fields)})
        for name, annotation in expected.items():
            assert hints[name] == annotation, f"{cls.__name__}.{name}: {hints[name]} != {annotation}"
        for f in dataclasses.fields(cls):
            assert f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING, (cls, f.name)
        assert cls.__dataclass_params__.frozen, cls


def test_built_records_document_every_attribute_from_the_schema() -> None:
    """The docstring of each built class lists every attribute with the schema's unit and description."""
    for cls, fields, _ in _BUILT:
        doc = cls.__doc__ or ""
        for key, f in attributes(fields):
            line = f"    {f.attr or f.name}{f' [{f.unit}]' if f.unit else ''}: {f.doc}"
            assert line + (f" (file: {key})" if f.attr else "") in doc.splitlines(), (cls.__name__, key)


def test_every_number_of_the_file_reaches_its_attribute() -> None:
    """The paper preset with the renamed and inline numbers of an agent and an edge changed: each attribute
    holds the file's value at its field's key."""
    doc = yaml.safe_load((REPO / "config" / "paper_5agents.yaml").read_text(encoding="utf-8"))
    edge = doc["edges"][0]
    edge.update(distance=2.6, distance_funnel={"rho_inf": 0.11, "decay": 1.7})
    edge.update(orientation_funnel={"rho_0": 1.98, "rho_inf": 0.12})
    doc["agents"][0]["measurement_noise"] = {"position_std": 0.003, "rotation_std": 0.004}
    built = spec.formation_from_dict(doc)
    agent, e = built.agents[0], built.edges[0]
    assert (agent.position_noise_std, agent.rotation_noise_std) == (0.003, 0.004)
    assert (e.rho_e_inf, e.decay_e, e.rho_psi_0, e.rho_psi_inf, e.decay_psi) == (0.11, 1.7, 1.98, 0.12, 1.5)
    assert e.d_des == 2.6 and agent.radius == doc["defaults"]["agent"]["radius"]
