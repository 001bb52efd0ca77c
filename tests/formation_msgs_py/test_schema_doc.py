"""The formation-file reference in docs/ is generated from the schema and kept in step."""

from __future__ import annotations

from pathlib import Path

from formation_msgs_py.schema import schema_markdown

REPO = Path(__file__).resolve().parents[2]


def test_docs_reference_matches_schema() -> None:
    """docs/formation_file.md holds the table `formation-check --schema` prints, verbatim."""
    doc = (REPO / "docs" / "formation_file.md").read_text(encoding="utf-8")
    assert schema_markdown() in doc, "regenerate: formation-check --schema (see docs/formation_file.md)"


def test_built_records_have_exactly_the_declared_fields() -> None:
    """One declaration: the simulation, controller, velocity-funnel and dynamics objects have the schema's fields."""
    import dataclasses

    from formation_msgs_py import spec
    from formation_msgs_py.schema import AGENT_FIELDS, SIMULATION_FIELDS, block

    pairs = [
        (spec.SimulationSpec, SIMULATION_FIELDS),
        (spec.ControllerGains, block(AGENT_FIELDS, "controller")),
        (spec.VelocityFunnel, block(AGENT_FIELDS, "controller", "velocity_funnel")),
        (spec.Dynamics, block(AGENT_FIELDS, "dynamics")),
    ]
    for cls, fields in pairs:
        assert [f.name for f in dataclasses.fields(cls)] == [f.name for f in fields], cls
        assert cls.__module__ == "formation_msgs_py.spec" and "Attributes" in cls.__doc__
