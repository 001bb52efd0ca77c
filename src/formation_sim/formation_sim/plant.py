"""Newton-Euler plant of N rigid bodies and its structure-preserving integrator.

Per agent, in the body frame (paper eq. system)::

    ṗ = R v_L,   Ṙ = R S(ω),   M v̇ + C(v) v + g(x) + w(x, v, t) = u
    M = diag(m I₃, J),  C(v) v = [m ω×v_L ; ω×Jω],  g(x) = −[m Rᵀ g_world ; 0]

Integration is RKMK4 (Runge-Kutta-Munthe-Kaas, order 4): R is advanced as R·exp(S(Θ)), so it
stays in SO(3) to rounding; p and v take the classical RK4 weights with the same stages.
Units: m, s, kg, kg·m², N, N·m; p in the world frame, v and u in the body frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from formation_msgs_py.so3 import cross, dexpinv_so3, exp_so3
from formation_msgs_py.spec import SimulatorView
from formation_sim.signals import SignalBank

#: u(t, state) for a controller evaluated at every integrator stage.
WrenchFunction = Callable[[float, "PlantState"], np.ndarray]


@dataclass
class PlantState:
    """World positions p (N,3) [m], R_world_body (N,3,3), body twists v (N,6) [m/s, rad/s]."""

    p: np.ndarray
    R: np.ndarray
    v: np.ndarray

    def copy(self) -> PlantState:
        return PlantState(self.p.copy(), self.R.copy(), self.v.copy())


class Plant:
    """The true dynamics of every agent of a formation (what only the simulator knows)."""

    def __init__(self, view: SimulatorView, rng: np.random.Generator | None = None) -> None:
        rng = rng if rng is not None else np.random.default_rng(view.simulation.seed)
        agents = view.agents
        self.n = len(agents)
        self.mass = np.array([a.dynamics.mass for a in agents])
        self.inertia = np.array([a.dynamics.inertia for a in agents])
        self.inertia_inv = np.linalg.inv(self.inertia)
        self.gravity = np.asarray(view.simulation.gravity, dtype=np.float64)
        self.has_gravity = bool(np.any(self.gravity != 0))
        self.disturbance = SignalBank([a.dynamics.disturbance for a in agents], rng)
        self.noise = SignalBank([a.dynamics.velocity_noise for a in agents], rng)

    def initial_state(self, view: SimulatorView) -> PlantState:
        return PlantState(
            np.array([a.position for a in view.agents], dtype=np.float64),
            np.array([a.R_world_body for a in view.agents], dtype=np.float64),
            np.array([a.twist for a in view.agents], dtype=np.float64),
        )

    def acceleration(self, t: float, s: PlantState, u: np.ndarray) -> np.ndarray:
        """v̇ (N,6) = M⁻¹(u − C(v)v − g(x) − w(x,v,t)), body frame."""
        vl = s.v[:, :3]
        w = s.v[:, 3:]
        f = u
        if self.disturbance.active:
            f = u - self.disturbance.evaluate(t, s.p, s.R, s.v)
        acc = np.empty_like(s.v)
        acc[:, :3] = f[:, :3] / self.mass[:, None] - cross(w, vl)
        if self.has_gravity:
            acc[:, :3] += np.einsum("nji,j->ni", s.R, self.gravity)
        Jw = np.einsum("nij,nj->ni", self.inertia, w)
        acc[:, 3:] = np.einsum("nij,nj->ni", self.inertia_inv, f[:, 3:] - cross(w, Jw))
        return acc

    def measured_velocity(self, t: float, s: PlantState) -> np.ndarray:
        """ṽ = v + n(x, t): the noisy body twists the agents receive (N,6)."""
        if not self.noise.active:
            return s.v.copy()
        return s.v + self.noise.evaluate(t, s.p, s.R, s.v)

    def step(self, t: float, s: PlantState, u: np.ndarray | WrenchFunction, h: float) -> PlantState:
        """One RKMK4 step of length h (s). ``u`` is held (N,6) or evaluated per stage."""
        wrench = u if callable(u) else (lambda _t, _s: u)
        R0 = s.R

        def rates(ts: float, st: PlantState) -> tuple[np.ndarray, np.ndarray]:
            pdot = np.einsum("nij,nj->ni", st.R, st.v[:, :3])
            return pdot, self.acceleration(ts, st, wrench(ts, st))

        p1, a1 = rates(t, s)
        K1 = s.v[:, 3:]
        th = 0.5 * h * K1
        s2 = PlantState(s.p + 0.5 * h * p1, R0 @ exp_so3(th), s.v + 0.5 * h * a1)
        p2, a2 = rates(t + 0.5 * h, s2)
        K2 = dexpinv_so3(th, s2.v[:, 3:])
        th = 0.5 * h * K2
        s3 = PlantState(s.p + 0.5 * h * p2, R0 @ exp_so3(th), s.v + 0.5 * h * a2)
        p3, a3 = rates(t + 0.5 * h, s3)
        K3 = dexpinv_so3(th, s3.v[:, 3:])
        th = h * K3
        s4 = PlantState(s.p + h * p3, R0 @ exp_so3(th), s.v + h * a3)
        p4, a4 = rates(t + h, s4)
        K4 = dexpinv_so3(th, s4.v[:, 3:])
        sixth = h / 6.0
        return PlantState(
            s.p + sixth * (p1 + 2 * p2 + 2 * p3 + p4),
            R0 @ exp_so3(sixth * (K1 + 2 * K2 + 2 * K3 + K4)),
            s.v + sixth * (a1 + 2 * a2 + 2 * a3 + a4),
        )
