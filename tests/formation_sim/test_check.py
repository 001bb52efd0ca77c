"""formation-check: exit 0 valid, 1 valid but unsafe, 2 invalid with the field named."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import yaml
from bin_helpers import executable

from formation_core.spec import load_formation
from formation_sim.cli import check
from formation_sim.core.loop import initial_rho_v0
from formation_sim.core.rates import rate_needs

REPO = Path(__file__).resolve().parents[2]


def test_paper_preset_is_valid_at_10khz(paper_path, capsys) -> None:
    assert check.main([str(paper_path)]) == 0
    out = capsys.readouterr().out
    assert "5 agents, 4 edges" in out and "VALID" in out
    # agent 1 needs ~3 kHz by t = 5 s (docs/controller.md): the printed need is the closed form's
    # (rate_needs, checked against docs/controller.md "Sampled-data implementation" in test_recorder.py),
    # not a golden number
    spec = load_formation(paper_path)
    need = next(n for n in rate_needs(spec, initial_rho_v0(spec)) if n.agent_id == "1")
    assert 2900 < need.at_end < 3100 and f"{need.at_end:.0f}" in out


def test_paper_preset_at_1khz_is_unsafe(paper_path, capsys) -> None:
    assert check.main([str(paper_path), "--control-rate", "1000"]) == 1
    err = capsys.readouterr().err
    assert "agent 1: control rate 1000 Hz is below" in err


def test_initial_error_near_its_bound_is_unsafe(paper_doc, tmp_path, capsys) -> None:
    """Edge 1-2 at 3.98 m with d_con = 4: within 1 % of the connectivity bound."""
    paper_doc["agents"][1]["position"] = [0.0, 0.0, 3.98]
    path = tmp_path / "near.yaml"
    path.write_text(yaml.safe_dump(paper_doc))
    assert check.main([str(path), "--quiet"]) == 1
    assert "edge 1-2: initial distance error within" in capsys.readouterr().err


def test_invalid_file_exits_2_naming_the_field(paper_doc, tmp_path, capsys) -> None:
    paper_doc["edges"][2]["distance"] = 4.5
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(paper_doc))
    assert check.main([str(path)]) == 2
    assert "edges[2].distance: 4.5 is not inside (d_col=2.0, d_con=4.0)" in capsys.readouterr().err


def test_four_mistakes_are_reported_in_one_run(paper_path, tmp_path, capsys) -> None:
    """A duplicate key, an unknown key, a matrix that is not a rotation and a distance beyond d_con:
    one run names all four (FILE:LINE:COL and field, in file order) and exits 2."""
    text = paper_path.read_text()
    for old, new in [
        ("  duration: 5.0\n", "  duration: 5.0\n  duration: 50.0\n"),
        ("    position: [-2.0, 3.25, 2.2]\n", "    position: [-2.0, 3.25, 2.2]\n    controller: {gama: 3.0}\n"),
        ("      project: true\n    dynamics:\n      mass: 0.807941\n", "    dynamics:\n      mass: 0.807941\n"),
        ("  - {tail: 3, head: 5}", "  - {tail: 3, head: 5, distance: 4.5}"),
    ]:
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    path = tmp_path / "four.yaml"
    path.write_text(text)
    assert check.main([str(path)]) == 2
    err = capsys.readouterr().err
    expected = [
        "simulation.duration: duplicate key (first at line 11)",
        "agents[1].orientation.matrix: is not a rotation",
        "agents[3].controller.gama: unknown key (did you mean 'gamma'?)",
        "edges[3].distance: 4.5 is not inside (d_col=2.0, d_con=4.0)",
    ]
    found = [re.search(rf"{re.escape(str(path))}:\d+:\d+: {re.escape(message)}", err) for message in expected]
    assert all(found), err
    assert [m.start() for m in found if m] == sorted(m.start() for m in found if m), err  # file order
    assert err.count(f"{path}:") == 4, err


def test_duration_without_a_control_step_is_invalid(paper_path, capsys) -> None:
    """--duration 1e-12 at 10 kHz takes no step: exit 2 (invalid, not merely unsafe), the option named."""
    assert check.main([str(paper_path), "--duration", "1e-12"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("formation-check: INVALID: --duration 1e-12 s is shorter than one control period: ")


def test_spanning_tree_option_prints_dropped_edges(paper_doc, tmp_path, capsys) -> None:
    paper_doc["edges"].append({"tail": 2, "head": 3})
    path = tmp_path / "cyclic.yaml"
    path.write_text(yaml.safe_dump(paper_doc))
    assert check.main([str(path), "--quiet"]) == 2
    assert check.main([str(path), "--spanning-tree"]) == 0
    assert "dropped edges (2, 3)" in capsys.readouterr().out


def test_console_script_and_schema(paper_path) -> None:
    """The installed console script runs; --schema prints the reference table."""
    exe = executable("formation-check")
    res = subprocess.run([str(exe), "--schema"], capture_output=True, text=True, check=True)
    assert "| `agents[].dynamics.mass` | float | required | kg |" in res.stdout
    res = subprocess.run(
        [str(exe), str(paper_path), "--control-rate", "1000", "--quiet"], capture_output=True, text=True
    )
    assert res.returncode == 1


def test_a_link_model_is_reported_and_one_whose_samples_are_never_used_is_unsafe(paper_doc, tmp_path, capsys) -> None:
    """Each link's largest age with none lost against its receiver's time-out, the losses in a row that make a
    measurement too old (at 2 % independent loss, 10 samples of 0.1 ms: 0.02^… per sample), and the note that
    only a campaign tells the margin; poses 0.2 s late, past the 0.1 s time-out, make the file unsafe."""
    paper_doc["defaults"]["agent"]["links"] = {
        "poses": {"delay": 0.0001, "loss": {"model": "independent", "probability": 0.02}}
    }
    path = tmp_path / "links.yaml"
    path.write_text(yaml.safe_dump(paper_doc))
    assert check.main([str(path)]) == 0
    out = capsys.readouterr().out
    # worst age 1 step (0.1 ms); time-out 0.1 s = 1000 steps: 1000 losses in a row to miss it
    assert re.search(r"poses 1->2 +0\.1 +100 +1000 +0\.02 independent", out), out
    assert "only a campaign can tell" in out
    paper_doc["agents"][2]["links"] = {"poses": {"delay": 0.2}}
    path.write_text(yaml.safe_dump(paper_doc))
    assert check.main([str(path), "--quiet"]) == 1
    assert (
        "link poses 3->1: its samples are 200 ms old with none lost, older than the 100 ms" in capsys.readouterr().err
    )
