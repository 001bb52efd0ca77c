"""Every formation file shipped in config/ runs its whole duration headless and passes, and a parameters
file's gains reach the headless run as they reach the agents."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from formation_core.spec import load_formation
from formation_sim.cli.headless import main, run_headless

pytestmark = pytest.mark.numeric

CONFIG = Path(__file__).resolve().parents[2] / "config"
PRESETS = sorted(CONFIG.glob("*.yaml"))


@pytest.mark.parametrize("preset", PRESETS, ids=lambda p: p.stem)
def test_every_preset_holds_over_its_whole_duration(preset: Path) -> None:
    """The preset as shipped, headless with sampled control at its own rate: PASS over its whole duration."""
    spec = load_formation(preset)
    summary = run_headless(spec, controller_mode="sampled").summary
    assert summary["verdict"] == "PASS", summary["first_violation"]
    assert summary["duration"] == spec.simulation.duration


def test_a_parameters_file_changes_the_headless_runs_gains(tmp_path: Path) -> None:
    """formation-headless --params-file FILE gives the run of a formation file that holds the same gains."""
    paper = CONFIG / "paper_5agents.yaml"
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    gamma: 12.0\n/agent_3/formation_agent:\n  ros__parameters:\n"
                      "    delta: 0.2\n")  # fmt: skip
    doc = yaml.safe_load(paper.read_text())
    doc["defaults"]["agent"]["controller"]["gamma"] = 12.0
    next(a for a in doc["agents"] if str(a["id"]) == "3").setdefault("controller", {})["delta"] = 0.2
    same = tmp_path / "same_gains.yaml"
    same.write_text(yaml.safe_dump(doc))
    outs = []
    for name, args in (("params", [str(paper), "--params-file", str(params)]), ("file", [str(same)])):
        out = tmp_path / name
        assert main([*args, "--out", str(out), "--duration", "0.2", "--no-plots", "--quiet"]) == 0
        outs.append(np.load(out / "trajectory.npz"))
    for key in ("p", "R", "v", "u"):
        np.testing.assert_array_equal(outs[0][key], outs[1][key], err_msg=key)
