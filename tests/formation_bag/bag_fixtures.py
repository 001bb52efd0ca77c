"""Session fixtures of synthetic lockstep bags (no ROS): this folder's conftest offers them to the bag
tests, and tests/formation_sim/test_offline.py (the offline runs from a bag) imports them too."""

from __future__ import annotations

from pathlib import Path

import pytest
from bag_helpers import PAPER, VIOLATING, paper_spec
from synth import SynthResult, write_run_bag


@pytest.fixture(scope="session")
def short_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, SynthResult]]:
    """A 0.15 s paper run at 1 kHz recorded in both storages (3 segments each)."""
    spec = paper_spec(duration=0.15, control_rate=1000.0, physics_rate=1000.0)
    out = {}
    for storage in ("mcap", "sqlite3"):
        bag = tmp_path_factory.mktemp(f"short_{storage}") / "bag"
        out[storage] = (
            bag,
            write_run_bag(spec, bag, formation_text=PAPER.read_text(), storage=storage, segment_seconds=0.05),
        )
    return out


@pytest.fixture(scope="session")
def violating_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, SynthResult]:
    """The paper run at a too-low control rate (700 Hz): agent 1 leaves its wz funnel at t ≈ 1.08 s."""
    spec = paper_spec(**VIOLATING)
    bag = tmp_path_factory.mktemp("violating") / "bag"
    result = write_run_bag(spec, bag, formation_text=PAPER.read_text(), segment_seconds=0.5, stop_on_violation=True)
    return bag, result
