"""Every pair of bodies watched, not only the tree's edges: clearance, contacts, and the contact policy."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from formation_core.spec import load_formation
from formation_sim.cli.headless import main, run_headless
from formation_sim.core.judge import Pairs, judge, pair_clearance
from formation_sim.views.figures import nearest_clearances

pytestmark = pytest.mark.numeric

DATA = Path(__file__).with_name("data")
CROSSING = DATA / "crossing_3agents.yaml"
PAPER = Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml"


def test_non_neighbours_steered_into_each_other_are_reported() -> None:
    """Agents 1 and 3, both neighbours of 2 only, touch at t = 0.2 s: the run passes its funnels and says
    so, and names the contact (pair, first time, smallest clearance) in summary.json clearance."""
    summary = run_headless(load_formation(CROSSING), controller_mode="sampled").summary
    assert summary["verdict"] == "PASS"
    c = summary["clearance"]
    assert c["policy"] == "report" and c["first_contact"] == {"t": 0.2, "pair": ["1", "3"]}
    assert c["pair"] == ["1", "3"] and c["min"] < 0.0
    assert [x["pair"] for x in c["contacts"]] == [["1", "3"]]


def test_a_contact_fails_the_run_where_the_file_says_so(tmp_path: Path, capsys) -> None:
    """--contact fail (simulation.contact: fail): the first contact is the first violation, FAIL, exit 1, and
    the verdict line names the pair; the default reports it beside a PASS, exit 0."""
    out = tmp_path / "fail"
    assert main([str(CROSSING), "--out", str(out), "--no-plots", "--contact", "fail"]) == 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["first_violation"] == {"t": 0.2, "kind": "contact", "pair": "1-3", "channel": "clearance"}
    assert "FAIL: first violation at t=0.2000 s: contact 1-3 (clearance)" in capsys.readouterr().out
    assert main([str(CROSSING), "--out", str(tmp_path / "report"), "--no-plots"]) == 0
    printed = capsys.readouterr().out
    assert "PASS: every funnel held over 1 s (worst margin" in printed
    assert "; but agents 1 and 3 touched at t=0.2000 s" in printed
    assert "CONTACT: agents 1 and 3 touched at t=0.2000 s" in printed


def test_the_run_core_and_the_judge_agree_on_every_pair() -> None:
    """The compiled check of every step and the judge over the recorded trajectory (the same formula and
    rule in two forms) give each pair the same smallest clearance, time and first contact, to the bit."""
    spec = load_formation(CROSSING, overrides={"record_rate": 1000.0})
    recorder = run_headless(spec, controller_mode="sampled").recorder
    arrays = recorder.arrays()
    again = judge(spec, arrays["t"], arrays["p"], arrays["R"])
    np.testing.assert_array_equal(again.min_clearance, recorder.judge.min_clearance)
    np.testing.assert_array_equal(again.min_clearance_t, recorder.judge.min_clearance_t)
    np.testing.assert_array_equal(again.contact_t, recorder.judge.contact_t)


def test_the_paper_scenario_touches_nothing() -> None:
    """The paper's bodies (radius 1 m) never touch: the smallest clearance is agents 3 and 5's at t = 0,
    2.103 m between their centres (the formula on the file's positions, exactly) minus both radii."""
    spec = load_formation(PAPER)
    c = run_headless(spec, controller_mode="sampled").summary["clearance"]
    assert c["first_contact"] is None and c["contacts"] == []
    assert c["pair"] == ["3", "5"] and c["t"] == 0.0
    p3, p5 = (tuple(spec.agent(a).position.tolist()) for a in ("3", "5"))
    assert c["min"] == pair_clearance(p3, p5, 2.0) == pytest.approx(0.10297, abs=1e-5)  # 5 figures, by hand


def test_clearance_is_distance_minus_both_radii() -> None:
    """Pairs in file order (i < j); the clearance of bodies at known places, and each agent's nearest."""
    spec = load_formation(CROSSING)
    pairs = Pairs(spec)
    assert pairs.ids == [("1", "2"), ("1", "3"), ("2", "3")]
    p = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 4.0, 0.0]])
    np.testing.assert_array_equal(pairs.clearances(p), [3.0 - 1.0, 4.0 - 1.0, 5.0 - 1.0])
    np.testing.assert_array_equal(nearest_clearances(spec, p[None])[0], [2.0, 2.0, 3.0])
