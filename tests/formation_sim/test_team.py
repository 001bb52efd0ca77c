"""The simulator's shadow of the agents (formation_sim.core.team.AgentTeam) on measurements by edge end."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from formation_agent.controller import AgentController
from formation_core.formation import agent_view, simulator_view
from formation_core.spec import load_formation
from formation_sim.core.measurement import Ends
from formation_sim.core.simulation import Simulation
from formation_sim.core.team import AgentTeam

pytestmark = pytest.mark.numeric

PAPER = Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml"


class Faults:
    """The recorder's fault() calls, in order."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, str, str]] = []

    def fault(self, t: float, kind: str, agent: str, detail: str = "") -> bool:
        self.calls.append((kind, agent, detail))
        return True


def test_team_answers_what_each_agent_answers() -> None:
    """Every agent's wrench from the end-indexed arrays equals its own controller's on the same poses
    (the same kernel on the same doubles: exactly)."""
    spec = load_formation(PAPER)
    meas = Simulation(simulator_view(spec)).sense()
    u, margin_v, errors = AgentTeam(spec).evaluate(meas, None)
    for i, a in enumerate(spec.agent_ids):
        own = AgentController(agent_view(spec, a)).compute(meas.t, meas.relative_poses[a], meas.velocities[i])
        np.testing.assert_array_equal(u[i], own.wrench)
        np.testing.assert_array_equal(margin_v[i], own.margin_v)
    assert errors == []


def test_a_missing_pose_is_a_measurement_fault_and_a_zero_wrench() -> None:
    """Agent 3 without its pose of agent 4: a ``measurement`` fault naming 4, zero wrench, and no
    ``controller`` error for it; the other agents answer as before."""
    spec = load_formation(PAPER)
    meas = Simulation(simulator_view(spec)).sense()
    full, _, _ = AgentTeam(spec).evaluate(meas, None)
    k = next(k for k, (i, j) in enumerate(zip(meas.ends.observer, meas.ends.target)) if (i, j) == ("3", "4"))
    in_range = meas.in_range.copy()
    in_range[k] = False
    partial = replace(meas, in_range=in_range)
    faults = Faults()
    u, _, errors = AgentTeam(spec).evaluate(partial, faults)  # type: ignore[arg-type]
    three = spec.agent_ids.index("3")
    assert faults.calls == [("measurement", "3", "4")]
    assert all(i != three for i, _ in errors)
    np.testing.assert_array_equal(u[three], np.zeros(6))
    others = [i for i in range(len(spec.agent_ids)) if i != three]
    np.testing.assert_array_equal(u[others], full[others])


def test_measurements_in_another_end_order_are_refused() -> None:
    spec = load_formation(PAPER)
    meas = Simulation(simulator_view(spec)).sense()
    ends = Ends(meas.ends.agent_ids, meas.ends.observer[::-1], meas.ends.target[::-1])
    shuffled = replace(meas, ends=ends)
    with pytest.raises(ValueError, match="order"):
        AgentTeam(spec).evaluate(shuffled, None)


def test_team_answers_at_the_stamps_time_on_what_an_agent_decodes() -> None:
    """At 3 kHz (a period of no whole number of ns) the team answers each agent as its own controller does
    from the step's messages: the rotations decoded from their quaternions, the time from the stamp, bit for bit."""
    from formation_msgs_py.codec import control_time, relative_pose_from_values, step_stamp_ns

    spec = load_formation(PAPER, overrides={"control_rate": 3000.0, "physics_rate": 3000.0})
    sim = Simulation(simulator_view(spec))
    team = AgentTeam(spec)
    own = {a: AgentController(agent_view(spec, a)) for a in spec.agent_ids}
    for k in range(4):
        meas = sim.sense()
        assert meas.ns == step_stamp_ns(k, 3000.0) == [0, 333_333, 666_667, 1_000_000][k]
        assert meas.t == control_time(meas.ns)
        assert (meas.t != k / 3000.0) == (k in (1, 2))  # the stamp's time, not k/rate
        u, _, _ = team.evaluate(meas, None)
        for i, a in enumerate(spec.agent_ids):
            poses = {}
            for end, (obs, tgt) in enumerate(zip(meas.ends.observer, meas.ends.target)):
                if obs == a:
                    poses[tgt] = relative_pose_from_values((*meas.p_rel[end], *meas.q_rel[end]))
                    np.testing.assert_array_equal(poses[tgt][1], meas.R_rel[end])  # the agent's decoding
            answer = own[a].compute(control_time(meas.ns), poses, meas.velocities[i])
            np.testing.assert_array_equal(u[i], answer.wrench)
        sim.advance(u)
