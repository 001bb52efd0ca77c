"""The formation-file reference in docs/ is generated from the schema and kept in step."""

from __future__ import annotations

from pathlib import Path

from formation_msgs_py.schema import schema_markdown

REPO = Path(__file__).resolve().parents[2]


def test_docs_reference_matches_schema() -> None:
    """docs/formation_file.md holds the table `formation-check --schema` prints, verbatim."""
    doc = (REPO / "docs" / "formation_file.md").read_text(encoding="utf-8")
    assert schema_markdown() in doc, "regenerate: formation-check --schema (see docs/formation_file.md)"
