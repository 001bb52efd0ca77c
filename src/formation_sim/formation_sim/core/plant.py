"""Newton-Euler plant of N rigid bodies and its structure-preserving integrator (compiled kernels).

Per agent, in the body frame (paper eq. system)::

    ṗ = R v_L,   Ṙ = R S(ω),   M v̇ + C(v) v + g(x) + w(x, v, t) = u
    M = diag(m I₃, J),  C(v) v = [m ω×v_L ; ω×Jω],  g(x) = −[m Rᵀ g_world ; 0]

The actuators saturate: each agent's force and torque norms are scaled down to its
``dynamics.max_force`` / ``max_torque`` before they enter the dynamics (:func:`saturate_into`).

Integration is RKMK4 (Runge-Kutta-Munthe-Kaas, order 4): R is advanced as R₀·exp(S(Θ)) with
Θ̇ = dexp⁻¹_{−Θ}(ω), so it stays in SO(3) to rounding; p and v take the classical RK4 weights
with the same stages (:func:`rkmk4_stage`, :func:`chart_rates`, :func:`rkmk4_combine`:
:func:`rkmk4_step` with the wrench held, the run core with the controller evaluated at every
stage). The kernels work in place on preallocated arrays (:class:`Workspace`): no allocation per
step. Units: m, s, kg,
kg·m², N, N·m; p in the world frame, v and u in the body frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from formation_core.formation import SimulatorView
from formation_core.numba_kernels import formula, kernel
from formation_core.so3 import cross3, dexpinv, exp_rows, matmul3, matrix_rows, matTvec3, matvec3, set3x3, sub3, vec3
from formation_sim.core.disturbances import (
    NONE,
    SignalParams,
    l1_norm,
    signal_params,
    signal_value,
    signals_at,
    signals_into,
)


@dataclass
class PlantState:
    """World positions p (N,3) [m], R_world_body (N,3,3), body twists v (N,6) [m/s, rad/s]."""

    p: np.ndarray
    R: np.ndarray
    v: np.ndarray

    def copy(self) -> PlantState:
        return PlantState(self.p.copy(), self.R.copy(), self.v.copy())


class PlantParams(NamedTuple):
    """The true dynamics (what only the simulator knows), arrays over agents."""

    mass: np.ndarray  # (N,) [kg]
    inertia: np.ndarray  # (N, 3, 3) [kg·m²]
    inertia_inv: np.ndarray  # (N, 3, 3)
    gravity: np.ndarray  # (3,) world frame [m/s²]
    max_force: np.ndarray  # (N,) actuator limit on ‖force‖ [N]
    max_torque: np.ndarray  # (N,) actuator limit on ‖torque‖ [N·m]
    disturbance: SignalParams
    noise: SignalParams


class Workspace(NamedTuple):
    """Scratch arrays of one RKMK4 step: the applied wrench and the four stages' rates and states."""

    u: np.ndarray  # (N, 6) the saturated wrench
    p_dot: np.ndarray  # (4, N, 3)
    v_dot: np.ndarray  # (4, N, 6)
    theta_dot: np.ndarray  # (4, N, 3)
    p: np.ndarray  # (N, 3) the current stage's state
    R: np.ndarray  # (N, 3, 3)
    v: np.ndarray  # (N, 6)
    theta: np.ndarray  # (N, 3)


def new_workspace(n: int) -> Workspace:
    return Workspace(
        np.zeros((n, 6)),
        np.zeros((4, n, 3)),
        np.zeros((4, n, 6)),
        np.zeros((4, n, 3)),
        np.zeros((n, 3)),
        np.zeros((n, 3, 3)),
        np.zeros((n, 6)),
        np.zeros((n, 3)),
    )


@formula
def saturate_into(u, plant, out):
    """out (N,6) = the wrenches the actuators apply: force and torque norms at most their limits.

    Directions are kept; a wrench within the limits is copied unchanged (bit for bit).
    """
    for i in range(u.shape[0]):
        for c in range(6):
            out[i, c] = u[i, c]
        for lo, limit in ((0, plant.max_force[i]), (3, plant.max_torque[i])):
            norm2 = u[i, lo] * u[i, lo] + u[i, lo + 1] * u[i, lo + 1] + u[i, lo + 2] * u[i, lo + 2]
            if norm2 > limit * limit:
                scale = limit / np.sqrt(norm2)
                for c in range(lo, lo + 3):
                    out[i, c] = scale * u[i, c]


@formula
def body_rates(t, p, R, v, u, plant, p_dot, v_dot):
    """Fill ṗ = R v_L (N,3) and v̇ = M⁻¹(u − C(v)v − g(x) − w(x, v, t)) (N,6) (eq. system)."""
    ref_first = l1_norm(p, 0)
    for i in range(p.shape[0]):
        force = (u[i, 0], u[i, 1], u[i, 2])
        torque = (u[i, 3], u[i, 4], u[i, 5])
        if plant.disturbance.kind[i] != NONE:
            trace = R[i, 0, 0] + R[i, 1, 1] + R[i, 2, 2]
            w = signal_value(plant.disturbance, i, t, ref_first, l1_norm(p, i), trace, v[i])
            force = (force[0] - w[0], force[1] - w[1], force[2] - w[2])
            torque = (torque[0] - w[3], torque[1] - w[4], torque[2] - w[5])
        lin = (v[i, 0], v[i, 1], v[i, 2])
        ang = (v[i, 3], v[i, 4], v[i, 5])
        R_world_body = matrix_rows(R[i])
        velocity_world = matvec3(R_world_body, lin)
        # m v̇_L = f − m ω×v_L + m Rᵀ g_world
        spin = cross3(ang, lin)
        gravity_body = matTvec3(R_world_body, vec3(plant.gravity))
        # J ω̇ = τ − ω×Jω
        J, J_inv = matrix_rows(plant.inertia[i]), matrix_rows(plant.inertia_inv[i])
        alpha = matvec3(J_inv, sub3(torque, cross3(ang, matvec3(J, ang))))
        for c in range(3):
            p_dot[i, c] = velocity_world[c]
            v_dot[i, c] = force[c] / plant.mass[i] - spin[c] + gravity_body[c]
            v_dot[i, 3 + c] = alpha[c]


@formula
def rkmk4_stage(c, p0, R0, v0, k, work):
    """The next stage's state at offset c [s] from stage k's rates, into ``work``.

    Θ = c·Θ̇_k, p = p₀ + c·ṗ_k, R = R₀ exp(S(Θ)), v = v₀ + c·v̇_k.
    """
    for i in range(p0.shape[0]):
        for x in range(3):
            work.theta[i, x] = c * work.theta_dot[k, i, x]
            work.p[i, x] = p0[i, x] + c * work.p_dot[k, i, x]
        set3x3(work.R[i], matmul3(matrix_rows(R0[i]), exp_rows(vec3(work.theta[i]))))
        for x in range(6):
            work.v[i, x] = v0[i, x] + c * work.v_dot[k, i, x]


@formula
def chart_rates(k, work):
    """Θ̇_k = dexp⁻¹_{−Θ}(ω) of every agent at the current stage."""
    for i in range(work.theta.shape[0]):
        rate = dexpinv(vec3(work.theta[i]), (work.v[i, 3], work.v[i, 4], work.v[i, 5]))
        for x in range(3):
            work.theta_dot[k, i, x] = rate[x]


@formula
def body_chart_rates(v, work):
    """Θ̇_0 = ω: the chart's rate at Θ = 0, the first stage."""
    for i in range(v.shape[0]):
        for x in range(3):
            work.theta_dot[0, i, x] = v[i, 3 + x]


@formula
def rkmk4_combine(h, p, R, v, work):
    """Advance (p, R, v) in place from the four stages' rates (classical weights 1, 2, 2, 1)."""
    w6 = h / 6.0
    pd, vd, td = work.p_dot, work.v_dot, work.theta_dot
    for i in range(p.shape[0]):
        for x in range(3):
            p[i, x] = p[i, x] + w6 * (pd[0, i, x] + 2 * pd[1, i, x] + 2 * pd[2, i, x] + pd[3, i, x])
            work.theta[i, x] = w6 * (td[0, i, x] + 2 * td[1, i, x] + 2 * td[2, i, x] + td[3, i, x])
        for x in range(6):
            v[i, x] = v[i, x] + w6 * (vd[0, i, x] + 2 * vd[1, i, x] + 2 * vd[2, i, x] + vd[3, i, x])
        set3x3(R[i], matmul3(matrix_rows(R[i]), exp_rows(vec3(work.theta[i]))))


@kernel
def rkmk4_step(t, p, R, v, u, h, plant, work):
    """One RKMK4 step of length h [s] with the commanded wrench u (N,6) held: (p, R, v) advance in place."""
    half = 0.5 * h
    saturate_into(u, plant, work.u)
    body_rates(t, p, R, v, work.u, plant, work.p_dot[0], work.v_dot[0])
    body_chart_rates(v, work)
    for k in range(3):
        c = h if k == 2 else half
        rkmk4_stage(c, p, R, v, k, work)
        body_rates(t + c, work.p, work.R, work.v, work.u, plant, work.p_dot[k + 1], work.v_dot[k + 1])
        chart_rates(k + 1, work)
    rkmk4_combine(h, p, R, v, work)


@kernel
def measured_velocity_into(t, p, R, v, noise, out):
    """out (N,6) = ṽ = v + n(x, t): the noisy body twists the agents receive."""
    for i in range(v.shape[0]):
        for c in range(6):
            out[i, c] = v[i, c]
    signals_into(noise, t, p, R, v, out)


class Plant:
    """The true dynamics of every agent of a formation, with its integrator."""

    def __init__(self, view: SimulatorView, rng: np.random.Generator | None = None) -> None:
        rng = rng if rng is not None else np.random.default_rng(view.simulation.seed)
        agents = view.agents
        self.n = len(agents)
        inertia = np.array([a.dynamics.inertia for a in agents], dtype=np.float64).reshape(self.n, 3, 3)
        self.params = PlantParams(
            np.array([a.dynamics.mass for a in agents], dtype=np.float64),
            inertia,
            np.linalg.inv(inertia),
            np.asarray(view.simulation.gravity, dtype=np.float64),
            np.array([a.dynamics.max_force for a in agents], dtype=np.float64),
            np.array([a.dynamics.max_torque for a in agents], dtype=np.float64),
            signal_params([a.dynamics.disturbance for a in agents], rng),
            signal_params([a.dynamics.velocity_noise for a in agents], rng),
        )
        self._work = new_workspace(self.n)

    @property
    def mass(self) -> np.ndarray:
        return self.params.mass

    @property
    def inertia(self) -> np.ndarray:
        return self.params.inertia

    def initial_state(self, view: SimulatorView) -> PlantState:
        return PlantState(
            np.array([a.position for a in view.agents], dtype=np.float64),
            np.array([a.R_world_body for a in view.agents], dtype=np.float64),
            np.array([a.twist for a in view.agents], dtype=np.float64),
        )

    def measured_velocity(self, t: float, s: PlantState) -> np.ndarray:
        """ṽ = v + n(x, t) (N,6)."""
        out = np.empty_like(s.v)
        measured_velocity_into(float(t), s.p, s.R, s.v, self.params.noise, out)
        return out

    def disturbance(self, t: float, s: PlantState) -> np.ndarray:
        """w(x, v, t) (N,6)."""
        return signals_at(self.params.disturbance, float(t), s.p, s.R, s.v)

    def saturate(self, u: np.ndarray) -> np.ndarray:
        """The wrenches (N,6) the actuators apply for the commanded ``u``."""
        out = np.empty((self.n, 6))
        saturate_into(np.asarray(u, dtype=np.float64), self.params, out)
        return out

    def step(self, t: float, s: PlantState, u: np.ndarray, h: float) -> PlantState:
        """One RKMK4 step of length h (s) with the wrenches u (N,6) held; a new state."""
        new = s.copy()
        rkmk4_step(float(t), new.p, new.R, new.v, np.asarray(u, dtype=np.float64), float(h), self.params, self._work)
        return new
