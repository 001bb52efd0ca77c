"""The link model (formation_sim.core.links): sensor rate, delay, jitter, loss, hold; the same deliveries
in the run core and in a simulator stepping one control step at a time."""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from formation_core.errors import FormationSpecError
from formation_core.formation import MeasurementLink, SignalModel, simulator_view
from formation_core.spec import formation_from_dict, load_formation
from formation_sim.cli.headless import run_headless
from formation_sim.core import links as lm
from formation_sim.core.recorder import RunRecorder
from formation_sim.core.simulation import Measurements, Simulation
from formation_sim.core.team import AgentTeam

pytestmark = pytest.mark.numeric

PAPER = Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml"
RATE = 10_000.0


def paper_with(links: dict[str, Any], duration: float = 0.2, **simulation: Any):
    """The paper scenario, shortened, with ``links`` under every agent (defaults.agent.links)."""
    doc = yaml.safe_load(PAPER.read_text())
    doc.setdefault("defaults", {}).setdefault("agent", {})["links"] = links
    doc["simulation"].update(duration=duration, **simulation)
    return formation_from_dict(doc, source=str(PAPER))


def one_link(rate=None, delay=0.0, jitter=None, loss=None, timeout=0.1) -> lm.Links:
    link = MeasurementLink(rate, delay, SignalModel(*(jitter or ("none", {}))), SignalModel(*(loss or ("none", {}))))
    return lm.new_links(lm.link_params(link, RATE, timeout)[None, :], 1, RATE)


def carry_steps(links: lm.Links, steps: int, seed: int = 1) -> list[int]:
    """Carry ``steps`` samples (value = step) through one link (interpreted); the held sample's step at each."""
    rng = np.random.default_rng(seed)
    held = []
    for k in range(steps):
        lm.carry(links, k, np.array([[float(k)]]), rng.random((1, 3)), RATE)
        held.append(int(links.held_step[0]))
        assert links.held_step[0] < 0 or links.held[0, 0] == links.held_step[0]  # the values travel with it
    return held


# --- the model's rules --------------------------------------------------------------------------


def test_a_delay_of_m_periods_is_m_steps_and_a_rate_of_f_over_n_holds_n_steps() -> None:
    """Delay exactly 3 periods: step k holds sample k − 3 (none before); 1/4 of the control rate: the samples
    of steps 0, 4, 8 … each held 4 steps; both: sample 4·floor((k − 3)/4)."""
    assert carry_steps(one_link(delay=3 / RATE), 12) == [-1, -1, -1, 0, 1, 2, 3, 4, 5, 6, 7, 8]
    assert carry_steps(one_link(rate=RATE / 4), 9) == [0, 0, 0, 0, 4, 4, 4, 4, 8]
    assert carry_steps(one_link(rate=RATE / 4, delay=3 / RATE), 12) == [-1, -1, -1, 0, 0, 0, 0, 4, 4, 4, 4, 8]


def test_a_30_hz_sensor_samples_at_the_first_step_after_each_period() -> None:
    """30 Hz at 10 kHz: samples at ceil(m · 10000/30): steps 0, 334, 667, 1000, 1334 …"""
    held = carry_steps(one_link(rate=30.0), 1400)
    assert sorted(set(held)) == [0, 334, 667, 1000, 1334]


def test_independent_loss_matches_its_probability() -> None:
    """p = 0.2 over 20 000 samples: the lost count lies within 4.5 standard deviations of N·p (a false alarm
    once in 150 000 runs; the seed is fixed, so the test is deterministic)."""
    links = one_link(loss=("independent", {"probability": 0.2}))
    carry_steps(links, 20_000)
    sent, lost = links.counts[0, lm.C_SENT], links.counts[0, lm.C_LOST]
    assert sent == 20_000
    assert abs(lost - 0.2 * sent) <= 4.5 * math.sqrt(sent * 0.2 * 0.8)
    assert links.counts[0, lm.C_ARRIVED] == sent - lost


def test_gilbert_elliott_loss_comes_in_bursts_at_its_stationary_rate() -> None:
    """P(good→bad) = 0.02, P(bad→good) = 0.2, lost only when bad: stationary loss 0.02/0.22 = 9.1 %, in
    bursts of mean length 1/0.2 = 5. Over 50 000 samples the rate lies within 4.5 standard deviations of a
    two-state chain (variance factor (1 + λ)/(1 − λ), λ = 1 − 0.22); the mean burst within 20 %."""
    gb, bg = 0.02, 0.2
    links = one_link(loss=("gilbert_elliott", {"p_good_bad": gb, "p_bad_good": bg, "loss_good": 0.0, "loss_bad": 1.0}))
    held = carry_steps(links, 50_000)
    n, lost = links.counts[0, lm.C_SENT], links.counts[0, lm.C_LOST]
    pi = gb / (gb + bg)
    lam = 1 - gb - bg
    assert abs(lost / n - pi) <= 4.5 * math.sqrt(pi * (1 - pi) * (1 + lam) / (1 - lam) / n)
    ages = np.diff(np.flatnonzero(np.diff(held) != 0))  # steps between new samples: 1 + each burst's length
    bursts = ages[ages > 1] - 1
    assert abs(bursts.mean() - 1 / bg) <= 0.2 / bg


def test_jitter_never_makes_a_sample_older_and_the_newest_wins() -> None:
    """Uniform jitter up to 5 periods over a 2-period delay: arrivals reorder, the held sample's step never
    goes back, every age lies in [2, 7] steps, and the overtaken samples are counted as superseded."""
    links = one_link(delay=2 / RATE, jitter=("uniform", {"max": 5 / RATE}))
    held = np.array(carry_steps(links, 5_000))
    got = held[held >= 0]
    assert np.all(np.diff(got) >= 0)
    ages = np.arange(len(held))[held >= 0] - got
    assert ages.min() >= 2 and ages.max() <= 7
    c = links.counts[0]
    assert c[lm.C_SUPERSEDED] > 100 and c[lm.C_ARRIVED] <= c[lm.C_SENT]
    assert links.age_max[0] == ages.max() and links.ages[0].sum() == len(got)


def test_exponential_jitter_stays_within_its_cut_off() -> None:
    """Mean 1 period truncated at 4: no sample takes more than 1 + 4 periods; the mean delay is below 1 + 1."""
    links = one_link(delay=1 / RATE, jitter=("exponential", {"mean": 1 / RATE, "max": 4 / RATE}))
    held = np.array(carry_steps(links, 5_000))
    ages = np.arange(len(held))[held >= 0] - held[held >= 0]
    assert ages.max() <= 5 and ages.min() >= 1


def test_the_same_seed_gives_the_same_deliveries() -> None:
    """Loss and jitter are drawn from the seed: the same seed, the same held samples; another, others."""
    model = {"delay": 2 / RATE, "jitter": ("uniform", {"max": 3 / RATE}), "loss": ("independent", {"probability": 0.3})}
    a, b, c = (carry_steps(one_link(**model), 2_000, seed) for seed in (5, 5, 6))
    assert a == b and a != c


# --- in a run ---------------------------------------------------------------------------------


def hand_loop(spec, feed, *, applied=None) -> dict[str, np.ndarray]:
    """The closed loop stepped by hand without a link model: ``feed(k, history)`` gives the Measurements the
    agents get at step k from the list of every step's sensed ones; ``applied(k, answers)`` the wrenches."""
    s = spec.simulation
    sim, team = Simulation(simulator_view(spec)), AgentTeam(spec)
    rec = RunRecorder(spec, record_every=1, control_rate=s.control_rate)
    n = round(s.duration * s.control_rate)
    history: list[Measurements] = []
    answers: list[np.ndarray] = []
    for k in range(n + 1):
        now = sim.sense()
        history.append(copy.deepcopy(now))
        meas = feed(k, history)
        u, margin_v, _ = team.evaluate(dataclasses.replace(meas, t=now.t, step=now.step, ns=now.ns), None)
        answers.append(np.array(u))
        rec.add(now.t, sim.state.p, sim.state.R, sim.state.v, u, margin_v)
        if k < n:
            sim.advance(answers[-1] if applied is None else applied(k, answers))
    return rec.arrays()


def without_links(spec):
    """``spec`` with every link ideal (the hand-built loops model the links themselves)."""
    ideal = paper_with({}).agents[0].links
    return dataclasses.replace(spec, agents=tuple(dataclasses.replace(a, links=ideal) for a in spec.agents))


def missing(meas: Measurements) -> Measurements:
    return dataclasses.replace(meas, in_range=np.zeros_like(meas.in_range))


def assert_same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    for key in ("t", "p", "R", "v", "u", "e", "psi"):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_a_run_with_poses_and_velocities_3_steps_late_is_the_hand_built_loop() -> None:
    """Every measurement 3 control periods late: the run core equals a loop feeding each controller the
    measurements of 3 steps before (nothing before step 3: the fault wrench), bit for bit."""
    spec = paper_with({"poses": {"delay": 3 / RATE}, "velocity": {"delay": 3 / RATE}}, record_rate=RATE)
    linked = run_headless(spec).recorder.arrays()
    by_hand = hand_loop(without_links(spec), lambda k, h: h[k - 3] if k >= 3 else missing(h[k]))
    assert_same(linked, by_hand)


def test_a_sensor_at_a_quarter_of_the_rate_is_each_sample_held_four_steps() -> None:
    """Poses and velocity sampled at 2.5 kHz: equal to a loop holding the measurements of steps 0, 4, 8 …"""
    spec = paper_with({"poses": {"rate": RATE / 4}, "velocity": {"rate": RATE / 4}}, record_rate=RATE)
    linked = run_headless(spec).recorder.arrays()
    by_hand = hand_loop(without_links(spec), lambda k, h: h[4 * (k // 4)])
    assert_same(linked, by_hand)


def test_a_wrench_2_steps_late_reaches_the_plant_2_steps_later() -> None:
    """The plant applies the answer of step k − 2 (zero before step 2); the recorded wrench is the answer."""
    spec = paper_with({"wrench": {"delay": 2 / RATE}}, record_rate=RATE)
    linked = run_headless(spec).recorder.arrays()
    zero = np.zeros((len(spec.agents), 6))
    by_hand = hand_loop(without_links(spec), lambda k, h: h[k], applied=lambda k, u: u[k - 2] if k >= 2 else zero)
    assert_same(linked, by_hand)


def test_stepping_one_step_at_a_time_gives_the_run_cores_deliveries() -> None:
    """Loss, jitter, a slow sensor and a late wrench: a simulator stepping one control step at a time (as the
    ROS simulator does) draws the same stream and gives the run core's run, bit for bit."""
    spec = paper_with(
        {
            "poses": {"rate": 200.0, "delay": 0.004, "jitter": {"distribution": "uniform", "max": 0.003},
                      "loss": {"model": "independent", "probability": 0.1}},
            "velocity": {"delay": 0.001, "loss": {"model": "gilbert_elliott", "p_good_bad": 0.01, "p_bad_good": 0.3}},
            "wrench": {"delay": 0.002, "loss": {"model": "independent", "probability": 0.05}},
        },
        duration=0.3,
        record_rate=RATE,
    )  # fmt: skip
    assert spec.has_links
    linked = run_headless(spec).recorder.arrays()
    stepped = hand_loop(spec, lambda k, h: h[k])
    assert_same(linked, stepped)


def test_ideal_links_are_no_link_model() -> None:
    """A file that spells out ideal links has none: its run is the paper's, bit for bit."""
    spec = paper_with({"poses": {"delay": 0.0}, "wrench": {"loss": {"model": "none"}}})
    assert not spec.has_links
    assert_same(run_headless(spec).recorder.arrays(), run_headless(paper_with({})).recorder.arrays())


# --- the file ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("links", "where", "message"),
    [
        ({"poses": {"delay": -0.01}}, "links.poses.delay", "must be >= 0"),
        (
            {"velocity": {"loss": {"model": "independent", "probability": 1.5}}},
            "links.velocity.loss.probability",
            "[0, 1]",
        ),
        ({"poses": {"rate": 20000.0}}, "links.poses.rate", "faster than simulation.control_rate"),
        ({"poses": {"jitter": {"max": 0.01}}}, "links.poses.jitter", "'distribution' key"),
        ({"wrench": {"delay": 9.0}}, "links.wrench.delay", "no sample would arrive"),
        (
            {"poses": {"loss": {"model": "gilbert_elliott", "p_good_bad": 0.1}}},
            "links.poses.loss.p_bad_good",
            "is required",
        ),
    ],
)
def test_bad_link_values_are_refused_with_the_element(tmp_path: Path, links, where: str, message: str) -> None:
    """Each bad value is refused with FILE:LINE:COL and the element's path."""
    doc = yaml.safe_load(PAPER.read_text())
    doc["agents"][2]["links"] = links
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises(FormationSpecError) as err:
        load_formation(path)
    text = str(err.value)
    assert f"{path}:" in text and f"agents[2].{where}" in text and message in text, text


def test_a_link_model_needs_the_sampled_controller() -> None:
    with pytest.raises(FormationSpecError, match=r"needs simulation\.controller: sampled"):
        paper_with({"poses": {"delay": 0.01}}, controller="continuous")


def test_an_edge_sets_one_ends_link() -> None:
    """edges[k].links.head replaces the head's links.poses for its measurement of the tail only."""
    doc = yaml.safe_load(PAPER.read_text())
    doc["edges"][0]["links"] = {"head": {"delay": 0.01}}
    spec = formation_from_dict(doc)
    assert spec.pose_link("2", "1").delay == 0.01
    assert spec.pose_link("1", "2").delay == 0.0 and spec.has_links
    view = simulator_view(spec)
    assert [(i, link.delay) for i, link in lm.end_links(view)][:3] == [(0, 0.0), (0, 0.0), (1, 0.01)]
