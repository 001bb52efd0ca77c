"""Paths and helpers shared by the bag tests (imported by conftest.py and the tests)."""

from __future__ import annotations

import sys
from pathlib import Path

from bin_helpers import executable
from process_hygiene import cpu_load  # noqa: F401  (re-exported for the bag tests)

from formation_core.formation import FormationSpec
from formation_core.spec import load_formation

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "config" / "paper_5agents.yaml"
HERE = Path(__file__).resolve().parent
#: the paper run at a too-low control rate: agent 1 leaves its wz velocity funnel at t ≈ 1.08 s
VIOLATING = {"duration": 1.3, "control_rate": 700.0, "physics_rate": 700.0}


def paper_spec(**overrides: float) -> FormationSpec:
    return load_formation(PAPER, overrides=overrides)


def script(name: str) -> list[str]:
    """Command line of a console script (found by tests/bin_helpers.py) or of a helper next to this file."""
    if name.endswith(".py"):
        return [sys.executable, str(HERE / name)]
    return [executable(name)]
