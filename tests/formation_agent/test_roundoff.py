"""The round-off bound of a controller step (formation_agent.roundoff): it holds every correct computation
of a step and refuses a wrong one, along the whole paper run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from formation_agent.controller import GAMMA, U, agent_step, new_outputs
from formation_agent.roundoff import UNIT, tolerance
from formation_core.formation import simulator_view
from formation_core.spec import load_formation
from formation_sim.core.simulation import Simulation
from formation_sim.core.team import AgentTeam

PAPER = Path(__file__).resolve().parents[2] / "config" / "paper_5agents.yaml"
pytestmark = pytest.mark.numeric


def other_answer(team: AgentTeam, i: int, meas, *, interpreted: bool = False, gamma_factor: float = 1.0, previous=None):
    """Agent i's wrench at ``meas`` computed otherwise than the team did: interpreted (numpy's exp and log
    instead of the compiled code's), with γ scaled, or from another step's measurements, on copies."""
    lo, hi = int(team.first_end[i]), int(team.first_end[i + 1])
    agents, start = team.agents.copy(), team.start.copy()
    agents[i, GAMMA] *= gamma_factor
    out, edge_out = new_outputs(len(team.ids), len(team.end_neighbours))
    source = meas if previous is None else previous
    step = agent_step.py_func if interpreted else agent_step
    step(meas.t, i, lo, hi, source.p_rel, source.R_rel, source.velocities[i], agents, team.ends, start, out, edge_out)
    return out[i, U : U + 6]


def test_the_bound_holds_correct_answers_and_refuses_wrong_ones_over_the_paper_run() -> None:
    """Every 250th step of the paper's 5 s, for every agent: the interpreted answer lies within the tolerance
    (a few per cent of it at most); an answer with γ off by one part in a million, or computed from the
    previous step's measurements, lies beyond it by a factor of more than 10 somewhere in the wrench."""
    spec = load_formation(PAPER)
    sim, team = Simulation(simulator_view(spec)), AgentTeam(spec)
    n_steps = round(spec.simulation.duration * spec.simulation.control_rate)
    ratios, wrong_gain, wrong_step = [], [], []
    previous = None
    for k in range(n_steps + 1):
        meas = sim.sense()
        u, _, _ = team.evaluate(meas, None)
        bounds = [team.bound(i, meas) for i in range(len(spec.agents))]  # every step: the funnel start's bound
        if k % 250 == 0 and previous is not None:
            for i, tol in enumerate(bounds):
                assert np.all(tol > 0) and np.all(np.isfinite(tol))
                ratios.append(np.max(np.abs(other_answer(team, i, meas, interpreted=True) - u[i]) / tol))
                wrong_gain.append(np.max(np.abs(other_answer(team, i, meas, gamma_factor=1 + 1e-6) - u[i]) / tol))
                wrong_step.append(np.max(np.abs(other_answer(team, i, meas, previous=previous) - u[i]) / tol))
        previous = meas
        if k < n_steps:
            sim.advance(u)
    assert max(ratios) < 0.1, max(ratios)
    assert min(wrong_gain) > 10, min(wrong_gain)
    assert min(wrong_step) > 10, min(wrong_step)


def test_the_tolerance_is_twice_two_bounds() -> None:
    """Two correct computations within the bound each of the exact value: 2·bound apart, and 2 for the second order."""
    assert tolerance(3.0) == 12.0
    assert UNIT == 2.0**-53


def test_an_agents_bounded_controller_bounds_as_the_witness_does() -> None:
    """BoundedController (formation-rerun's) gives the wrench tolerance the simulator's team gives for the
    same agent and step, bit for bit; zero after a fault output (the zero wrench is exact); a reset starts
    the velocity funnel's bound again."""
    from formation_agent.controller import ERROR
    from formation_agent.roundoff import BoundedController
    from formation_core.formation import agent_view

    spec = load_formation(PAPER)
    sim, team = Simulation(simulator_view(spec)), AgentTeam(spec)
    i, agent = 2, spec.agent_ids[2]
    view = agent_view(spec, agent)
    ctrl = BoundedController(view)
    lo = int(team.first_end[i])
    for _ in range(30):
        meas = sim.sense()
        u, _, _ = team.evaluate(meas, None)
        poses = {ie.neighbour: (meas.p_rel[lo + k], meas.R_rel[lo + k]) for k, ie in enumerate(view.edges)}
        out = ctrl.compute(meas.t, poses, meas.velocities[i])
        np.testing.assert_array_equal(out.wrench, u[i])
        np.testing.assert_array_equal(ctrl.wrench_tolerance, team.bound(i, meas))
        sim.advance(u)
    assert set(ctrl.tolerances()) == {"wrench", "v_des", "xi_v", "margin_v", "e", "psi", "xi_e", "xi_psi",
                                      "margin_e", "margin_psi"}  # fmt: skip
    assert ctrl.fault_output(meas.t, "missing").level == ERROR
    assert not ctrl.wrench_tolerance.any()
    ctrl.reset()
    fresh = BoundedController(view)
    meas = sim.sense()
    poses = {ie.neighbour: (meas.p_rel[lo + k], meas.R_rel[lo + k]) for k, ie in enumerate(view.edges)}
    ctrl.compute(meas.t, poses, meas.velocities[i])
    fresh.compute(meas.t, poses, meas.velocities[i])
    np.testing.assert_array_equal(ctrl.wrench_tolerance, fresh.wrench_tolerance)
