"""The control rate each agent needs (NOTES.md, "Sampled-data implementation").

Near ξ_v = 0 the wrench is u ≈ −4γ ρ_v⁻² e_v per channel, so agent i's velocity loop is
v̇ ≈ −M⁻¹ K(t) v with K = diag(4γ/ρ_v,ℓ(t)²). A zero-order-hold controller at rate f_s is
stable only if f_s > λ_max(M⁻¹K(t))/2. ρ_v decreases, so the need grows over the run and is
largest at the end. ``auto`` velocity funnels are evaluated as the agent will: from e_v(0),
computed with the agent core on the initial measurements.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from formation_agent.controller import AgentController
from formation_msgs_py import funnels
from formation_msgs_py.spec import FormationSpec, agent_view, simulator_view
from formation_sim.simulation import Simulation


@dataclass(frozen=True)
class RateNeed:
    """Control rate agent ``agent_id`` needs: at t=0 and at the end of the run (Hz)."""

    agent_id: str
    at_start: float
    at_end: float
    rho_v0: np.ndarray
    #: first time (s) at which the configured control rate stops being enough, or None
    insufficient_from: float | None


def _need(M_inv: np.ndarray, gamma: float, rho: np.ndarray) -> float:
    K = np.diag(4.0 * gamma / rho**2)
    return float(np.max(np.abs(np.linalg.eigvals(M_inv @ K)))) / 2.0


def rate_needs(spec: FormationSpec) -> list[RateNeed]:
    """The control rate every agent of ``spec`` needs over ``simulation.duration``."""
    sim = Simulation(simulator_view(spec))
    meas = sim.sense()
    T = spec.simulation.duration
    f_s = spec.simulation.control_rate
    grid = np.linspace(0.0, T, 401)
    out = []
    for i, a in enumerate(spec.agents):
        ctrl = AgentController(agent_view(spec, a.id))
        try:
            ctrl.compute(0.0, meas.relative_poses[a.id], meas.velocities[i])
            rho_v0 = np.array(ctrl.rho_v0)
        except Exception:
            rho_v0 = np.full(6, a.controller.velocity_funnel.auto_offset)
        vf = a.controller.velocity_funnel
        M = np.zeros((6, 6))
        M[:3, :3] = np.eye(3) * a.dynamics.mass
        M[3:, 3:] = a.dynamics.inertia
        M_inv = np.linalg.inv(M)
        rho = funnels.exp_decay(
            rho_v0[None, :], np.array(vf.rho_inf)[None, :], np.array(vf.decay)[None, :], grid[:, None]
        )
        needs = np.array([_need(M_inv, a.controller.gamma, r) for r in rho])
        over = np.nonzero(needs > f_s)[0]
        out.append(RateNeed(a.id, needs[0], float(needs.max()), rho_v0, float(grid[over[0]]) if over.size else None))
    return out
