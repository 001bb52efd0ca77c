"""The control rate each agent needs (docs/controller.md, "Sampled-data implementation").

Near ξ_v = 0 the wrench is u ≈ −4γ ρ_v⁻² e_v per channel, so agent i's velocity loop is
v̇ ≈ −M⁻¹ K(t) v with K = diag(4γ/ρ_v,ℓ(t)²). A zero-order-hold controller at rate f_s is
stable only if f_s > λ_max(M⁻¹K(t))/2 (:func:`rate_need`), and fixed-step RK4 on the continuous
closed loop only if λ_max·h < 2.785 (:attr:`RateNeed.physics_step`). ρ_v decreases, so the need grows over
the run and is largest at the end. ``auto`` velocity funnels are evaluated as the agent will:
from e_v(0), computed by the agents' controllers on the initial measurements.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from formation_core import funnels
from formation_core.formation import FormationSpec

#: Fixed-step RK4 is stable on ẋ = −λx for λ·h < 2.785 (the real stability interval of RK4).
RK4_STABILITY = 2.785


@dataclass(frozen=True)
class RateNeed:
    """Control rate agent ``agent_id`` needs: at t=0 and at the end of the run (Hz)."""

    agent_id: str
    at_start: float
    at_end: float
    rho_v0: np.ndarray
    #: first time (s) at which the configured control rate stops being enough, or None
    insufficient_from: float | None

    @property
    def physics_step(self) -> float:
        """Largest RK4 step [s] for the continuous closed loop: λ·h < 2.785 with λ = 2·(rate need).

        The need is largest at the end of the run (ρ_v decreases), so this holds over the run.
        """
        return RK4_STABILITY / (2.0 * self.at_end)


def rate_need(M: np.ndarray, gamma: float, rho_v: np.ndarray) -> np.ndarray:
    """f_s [Hz] = λ_max(M⁻¹ diag(4γ/ρ_v²))/2 for a (6,6) inertia matrix M and ρ_v of shape (..., 6)."""
    rho_v = np.asarray(rho_v, dtype=np.float64)
    with np.errstate(over="ignore"):  # a huge e_v(0) gives a huge ρ_v0: its need is 0, not a warning
        K = 4.0 * gamma / rho_v**2
    A = np.linalg.inv(M) * K[..., None, :]  # M⁻¹ diag(K): column ℓ scaled by K_ℓ
    return np.max(np.abs(np.linalg.eigvals(A)), axis=-1) / 2.0


def mass_matrix(mass: float, inertia: np.ndarray) -> np.ndarray:
    """M = diag(m I₃, J) (6,6)."""
    M = np.zeros((6, 6))
    M[:3, :3] = np.eye(3) * mass
    M[3:, 3:] = inertia
    return M


def rate_needs(spec: FormationSpec, rho_v0s: np.ndarray) -> list[RateNeed]:
    """The control rate every agent of ``spec`` needs over ``simulation.duration``, from the velocity
    funnels ``rho_v0s`` (N,6) the agents set at their first step
    (:func:`formation_sim.core.loop.initial_rho_v0`)."""
    T = spec.simulation.duration
    f_s = spec.simulation.control_rate
    grid = np.linspace(0.0, T, 401)
    out = []
    for a, rho_v0 in zip(spec.agents, rho_v0s):
        vf = a.controller.velocity_funnel
        rho = funnels.rho(grid[:, None], rho_v0[None, :], np.array(vf.rho_inf)[None, :], np.array(vf.decay)[None, :])
        needs = rate_need(mass_matrix(a.dynamics.mass, np.asarray(a.dynamics.inertia)), a.controller.gamma, rho)
        over = np.nonzero(needs > f_s)[0]
        out.append(RateNeed(a.id, needs[0], float(needs.max()), rho_v0, float(grid[over[0]]) if over.size else None))
    return out
