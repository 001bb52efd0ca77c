"""Newton-Euler plant of N rigid bodies and its structure-preserving integrator (compiled kernels).

Per agent, in the body frame (paper eq. system)::

    ṗ = R v_L,   Ṙ = R S(ω),   M v̇ + C(v) v + g(x) + w(x, v, t) = u
    M = diag(m I₃, J),  C(v) v = [m ω×v_L ; ω×Jω],  g(x) = −[m Rᵀ g_world ; 0]

The actuators saturate: each agent's force and torque norms are scaled down to its
``dynamics.max_force`` / ``max_torque`` before they enter the dynamics (:func:`saturate`).

Integration is RKMK4 (Runge-Kutta-Munthe-Kaas, order 4): R is advanced as R₀·exp(S(Θ)) with
Θ̇ = dexp⁻¹_{−Θ}(ω), so it stays in SO(3) to rounding; p and v take the classical RK4 weights
with the same stages (:func:`rkmk4_stage`, :func:`rkmk4_combine`; :func:`rkmk4_step` with the
wrench held, the run core with the controller evaluated at every stage). Units: m, s, kg,
kg·m², N, N·m; p in the world frame, v and u in the body frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from formation_msgs_py.compiled import kernel
from formation_msgs_py.so3 import cross3, dexpinv_so3, exp_so3, matmul3, matvec3
from formation_msgs_py.spec import SimulatorView
from formation_sim.signals import NONE, SignalParams, signal_params, signal_value, signals_at


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


@kernel
def saturate(u, plant):
    """The wrenches (N,6) the actuators apply: force and torque norms at most their limits, directions kept.

    A wrench within the limits is returned unchanged (bit for bit).
    """
    out = u.copy()
    for i in range(u.shape[0]):
        for lo, limit in ((0, plant.max_force[i]), (3, plant.max_torque[i])):
            norm2 = u[i, lo] ** 2 + u[i, lo + 1] ** 2 + u[i, lo + 2] ** 2
            if norm2 > limit * limit:
                out[i, lo : lo + 3] = limit / np.sqrt(norm2) * u[i, lo : lo + 3]
    return out


@kernel
def body_rates(t, p, R, v, u, plant):
    """(ṗ (N,3), v̇ (N,6)): ṗ = R v_L and v̇ = M⁻¹(u − C(v)v − g(x) − w(x, v, t)) (eq. system)."""
    n = p.shape[0]
    p_dot = np.empty((n, 3))
    v_dot = np.empty((n, 6))
    ref_first = np.abs(p[0]).sum()
    for i in range(n):
        f = u[i].copy()
        if plant.disturbance.kind[i] != NONE:
            trace = R[i, 0, 0] + R[i, 1, 1] + R[i, 2, 2]
            f = f - signal_value(plant.disturbance, i, t, ref_first, np.abs(p[i]).sum(), trace, v[i])
        lin, ang = v[i, :3], v[i, 3:]
        p_dot[i] = matvec3(R[i], lin)
        # m v̇_L = f − m ω×v_L + m Rᵀ g_world
        v_dot[i, :3] = f[:3] / plant.mass[i] - cross3(ang, lin) + matvec3(R[i].T, plant.gravity)
        # J ω̇ = τ − ω×Jω
        v_dot[i, 3:] = matvec3(plant.inertia_inv[i], f[3:] - cross3(ang, matvec3(plant.inertia[i], ang)))
    return p_dot, v_dot


@kernel
def rkmk4_stage(c, p0, R0, v0, p_dot, v_dot, theta_dot):
    """The stage state at offset c [s]: (Θ, p, R, v) with Θ = c·Θ̇, R = R₀ exp(S(Θ))."""
    theta = c * theta_dot
    R = np.empty_like(R0)
    for i in range(R0.shape[0]):
        R[i] = matmul3(R0[i], exp_so3(theta[i]))
    return theta, p0 + c * p_dot, R, v0 + c * v_dot


@kernel
def chart_rates(theta, v):
    """Θ̇ = dexp⁻¹_{−Θ}(ω) of every agent (N,3)."""
    out = np.empty_like(theta)
    for i in range(theta.shape[0]):
        out[i] = dexpinv_so3(theta[i], v[i, 3:])
    return out


@kernel
def rkmk4_combine(h, p0, R0, v0, p_dots, v_dots, theta_dots):
    """The step's end from the four stages' rates (classical weights 1, 2, 2, 1)."""
    w6 = h / 6.0
    p = p0 + w6 * (p_dots[0] + 2 * p_dots[1] + 2 * p_dots[2] + p_dots[3])
    v = v0 + w6 * (v_dots[0] + 2 * v_dots[1] + 2 * v_dots[2] + v_dots[3])
    theta = w6 * (theta_dots[0] + 2 * theta_dots[1] + 2 * theta_dots[2] + theta_dots[3])
    R = np.empty_like(R0)
    for i in range(R0.shape[0]):
        R[i] = matmul3(R0[i], exp_so3(theta[i]))
    return p, R, v


@kernel
def rkmk4_step(t, p, R, v, u, h, plant):
    """One RKMK4 step of length h [s] with the commanded wrench u (N,6) held: the new (p, R, v)."""
    half = 0.5 * h
    u = saturate(u, plant)
    pd1, vd1 = body_rates(t, p, R, v, u, plant)
    K1 = np.ascontiguousarray(v[:, 3:])
    th2, p2, R2, v2 = rkmk4_stage(half, p, R, v, pd1, vd1, K1)
    pd2, vd2 = body_rates(t + half, p2, R2, v2, u, plant)
    K2 = chart_rates(th2, v2)
    th3, p3, R3, v3 = rkmk4_stage(half, p, R, v, pd2, vd2, K2)
    pd3, vd3 = body_rates(t + half, p3, R3, v3, u, plant)
    K3 = chart_rates(th3, v3)
    th4, p4, R4, v4 = rkmk4_stage(h, p, R, v, pd3, vd3, K3)
    pd4, vd4 = body_rates(t + h, p4, R4, v4, u, plant)
    K4 = chart_rates(th4, v4)
    return rkmk4_combine(h, p, R, v, (pd1, pd2, pd3, pd4), (vd1, vd2, vd3, vd4), (K1, K2, K3, K4))


@kernel
def measured_velocity(t, p, R, v, noise):
    """ṽ = v + n(x, t): the noisy body twists the agents receive (N,6)."""
    return v + signals_at(noise, t, p, R, v)


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
        return measured_velocity(float(t), s.p, s.R, s.v, self.params.noise)

    def disturbance(self, t: float, s: PlantState) -> np.ndarray:
        """w(x, v, t) (N,6)."""
        return signals_at(self.params.disturbance, float(t), s.p, s.R, s.v)

    def saturate(self, u: np.ndarray) -> np.ndarray:
        """The wrenches (N,6) the actuators apply for the commanded ``u``."""
        return saturate(np.asarray(u, dtype=np.float64), self.params)

    def acceleration(self, t: float, s: PlantState, u: np.ndarray) -> np.ndarray:
        """v̇ (N,6) = M⁻¹(sat(u) − C(v)v − g(x) − w(x,v,t)), body frame."""
        return body_rates(float(t), s.p, s.R, s.v, self.saturate(u), self.params)[1]

    def step(self, t: float, s: PlantState, u: np.ndarray, h: float) -> PlantState:
        """One RKMK4 step of length h (s) with the wrenches u (N,6) held."""
        p, R, v = rkmk4_step(float(t), s.p, s.R, s.v, np.asarray(u, dtype=np.float64), float(h), self.params)
        return PlantState(p, R, v)
