"""Newton-Euler plant of N rigid bodies and its structure-preserving integrator.

Per agent, in the body frame (paper eq. system)::

    ṗ = R v_L,   Ṙ = R S(ω),   M v̇ + C(v) v + g(x) + w(x, v, t) = u
    M = diag(m I₃, J),  C(v) v = [m ω×v_L ; ω×Jω],  g(x) = −[m Rᵀ g_world ; 0]

The actuators saturate: each agent's force and torque norms are scaled down to its
``dynamics.max_force`` / ``max_torque`` before they enter the dynamics (:meth:`Plant.saturate`).

Integration is RKMK4 (Runge-Kutta-Munthe-Kaas, order 4): R is advanced as R₀·exp(S(Θ)) with
Θ̇ = dexp⁻¹_{−Θ}(ω), so it stays in SO(3) to rounding; p and v take the classical RK4 weights
with the same stages. Units: m, s, kg, kg·m², N, N·m; p in the world frame, v and u in the
body frame.

The step is written with Python floats, agent by agent: for 3-vectors numpy's per-call
overhead costs several times the arithmetic, and the simulator runs this at up to 20 kHz. The
public state (:class:`PlantState`) stays numpy.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from formation_msgs_py.spec import SimulatorView
from formation_sim.signals import SignalBank

#: u(t, state) for a controller evaluated at every integrator stage.
WrenchFunction = Callable[[float, "PlantState"], np.ndarray]

_sin, _cos, _sqrt, _tan = math.sin, math.cos, math.sqrt, math.tan


@dataclass
class PlantState:
    """World positions p (N,3) [m], R_world_body (N,3,3), body twists v (N,6) [m/s, rad/s]."""

    p: np.ndarray
    R: np.ndarray
    v: np.ndarray

    def copy(self) -> PlantState:
        return PlantState(self.p.copy(), self.R.copy(), self.v.copy())


def _exp(tx: float, ty: float, tz: float) -> tuple[float, ...]:
    """exp(S(θ)) row-major: cos·I + (sin θ/θ)·S(θ) + ((1 − cos)/θ²)·θθᵀ (series near 0)."""
    a2 = tx * tx + ty * ty + tz * tz
    if a2 < 1e-8:
        A = 1.0 - a2 / 6.0 + a2 * a2 / 120.0
        B = 0.5 - a2 / 24.0 + a2 * a2 / 720.0
        C = 1.0 - a2 / 2.0 + a2 * a2 / 24.0
    else:
        a = _sqrt(a2)
        A = _sin(a) / a
        C = _cos(a)
        B = (1.0 - C) / a2
    return (
        C + B * tx * tx, B * tx * ty - A * tz, B * tx * tz + A * ty,
        B * ty * tx + A * tz, C + B * ty * ty, B * ty * tz - A * tx,
        B * tz * tx - A * ty, B * tz * ty + A * tx, C + B * tz * tz,
    )  # fmt: skip


def _dexpinv(tx: float, ty: float, tz: float, wx: float, wy: float, wz: float) -> tuple[float, float, float]:
    """dexp⁻¹_{−Θ}(ω) = ω + ½ Θ×ω + c·Θ×(Θ×ω), c = (1 − (θ/2)cot(θ/2))/θ²."""
    a2 = tx * tx + ty * ty + tz * tz
    if a2 < 1e-6:
        c = 1.0 / 12.0 + a2 / 720.0
    else:
        half = 0.5 * _sqrt(a2)
        c = (1.0 - half / _tan(half)) / a2
    cx, cy, cz = ty * wz - tz * wy, tz * wx - tx * wz, tx * wy - ty * wx
    return (
        wx + 0.5 * cx + c * (ty * cz - tz * cy),
        wy + 0.5 * cy + c * (tz * cx - tx * cz),
        wz + 0.5 * cz + c * (tx * cy - ty * cx),
    )


def _rot(R0: list[list[float]], E: tuple[float, ...]) -> tuple[float, ...]:
    """R0 @ E for R0 nested rows and E row-major (9 floats)."""
    (a, b, c), (d, e, f), (g, h, i) = R0
    e0, e1, e2, e3, e4, e5, e6, e7, e8 = E
    return (
        a * e0 + b * e3 + c * e6, a * e1 + b * e4 + c * e7, a * e2 + b * e5 + c * e8,
        d * e0 + e * e3 + f * e6, d * e1 + e * e4 + f * e7, d * e2 + e * e5 + f * e8,
        g * e0 + h * e3 + i * e6, g * e1 + h * e4 + i * e7, g * e2 + h * e5 + i * e8,
    )  # fmt: skip


class Plant:
    """The true dynamics of every agent of a formation (what only the simulator knows)."""

    def __init__(self, view: SimulatorView, rng: np.random.Generator | None = None) -> None:
        rng = rng if rng is not None else np.random.default_rng(view.simulation.seed)
        agents = view.agents
        self.n = len(agents)
        self.mass = np.array([a.dynamics.mass for a in agents])
        self.inertia = np.array([a.dynamics.inertia for a in agents])
        self.inertia_inv = np.linalg.inv(self.inertia)
        self._limits = [(a.dynamics.max_force, a.dynamics.max_torque) for a in agents]
        self.gravity = np.asarray(view.simulation.gravity, dtype=np.float64)
        self.has_gravity = bool(np.any(self.gravity != 0))
        self.disturbance = SignalBank([a.dynamics.disturbance for a in agents], rng)
        self.noise = SignalBank([a.dynamics.velocity_noise for a in agents], rng)
        # per agent, as floats: m, J (9), J⁻¹ (9), disturbance evaluator
        self._agents = [
            (
                float(self.mass[i]),
                tuple(self.inertia[i].ravel().tolist()),
                tuple(self.inertia_inv[i].ravel().tolist()),
                self.disturbance.signals[i],
            )
            for i in range(self.n)
        ]
        self._g = tuple(self.gravity.tolist())

    def initial_state(self, view: SimulatorView) -> PlantState:
        return PlantState(
            np.array([a.position for a in view.agents], dtype=np.float64),
            np.array([a.R_world_body for a in view.agents], dtype=np.float64),
            np.array([a.twist for a in view.agents], dtype=np.float64),
        )

    def saturate(self, U: list[list[float]]) -> list[list[float]]:
        """The wrenches (N rows of 6) the actuators apply: force and torque norms at most their limits."""
        out = U
        for i, (max_f, max_t) in enumerate(self._limits):
            fx, fy, fz, tx, ty, tz = U[i]
            f2 = fx * fx + fy * fy + fz * fz
            t2 = tx * tx + ty * ty + tz * tz
            if f2 > max_f * max_f or t2 > max_t * max_t:
                if out is U:
                    out = list(U)
                kf = max_f / _sqrt(f2) if f2 > max_f * max_f else 1.0
                kt = max_t / _sqrt(t2) if t2 > max_t * max_t else 1.0
                out[i] = [kf * fx, kf * fy, kf * fz, kt * tx, kt * ty, kt * tz]
        return out

    def measured_velocity(self, t: float, s: PlantState) -> np.ndarray:
        """ṽ = v + n(x, t): the noisy body twists the agents receive (N,6)."""
        if not self.noise.active:
            return s.v.copy()
        return s.v + self.noise.evaluate(t, s.p, s.R, s.v)

    def acceleration(self, t: float, s: PlantState, u: np.ndarray) -> np.ndarray:
        """v̇ (N,6) = M⁻¹(u − C(v)v − g(x) − w(x,v,t)), body frame."""
        P = s.p.tolist()
        Rf = [r[0] + r[1] + r[2] for r in s.R.tolist()]
        U = self.saturate(np.asarray(u, dtype=np.float64).tolist())
        _, acc = self._rates(t, P, Rf, s.v.tolist(), U)
        return np.array(acc)

    def _rates(
        self, t: float, P: list[list[float]], Rf: list, V: list[list[float]], U: list[list[float]]
    ) -> tuple[list[tuple[float, float, float]], list[tuple[float, ...]]]:
        """(ṗ, v̇) of every agent; Rf holds row-major 9-sequences."""
        p1 = P[0]
        ref_first = abs(p1[0]) + abs(p1[1]) + abs(p1[2])
        gx, gy, gz = self._g
        gravity = self.has_gravity
        pdots = []
        accs = []
        for i, (m, J, Ji, dist) in enumerate(self._agents):
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = Rf[i]
            v = V[i]
            vx, vy, vz, wx, wy, wz = v
            fx, fy, fz, tx, ty, tz = U[i]
            if dist is not None:
                pi = P[i]
                w = dist(t, ref_first, abs(pi[0]) + abs(pi[1]) + abs(pi[2]), r00 + r11 + r22, v)
                fx, fy, fz, tx, ty, tz = fx - w[0], fy - w[1], fz - w[2], tx - w[3], ty - w[4], tz - w[5]
            pdots.append(
                (r00 * vx + r01 * vy + r02 * vz, r10 * vx + r11 * vy + r12 * vz, r20 * vx + r21 * vy + r22 * vz)
            )
            ax = fx / m - (wy * vz - wz * vy)
            ay = fy / m - (wz * vx - wx * vz)
            az = fz / m - (wx * vy - wy * vx)
            if gravity:  # Rᵀ g_world
                ax += r00 * gx + r10 * gy + r20 * gz
                ay += r01 * gx + r11 * gy + r21 * gz
                az += r02 * gx + r12 * gy + r22 * gz
            j0, j1, j2, j3, j4, j5, j6, j7, j8 = J
            hx, hy, hz = j0 * wx + j1 * wy + j2 * wz, j3 * wx + j4 * wy + j5 * wz, j6 * wx + j7 * wy + j8 * wz
            tx -= wy * hz - wz * hy
            ty -= wz * hx - wx * hz
            tz -= wx * hy - wy * hx
            k0, k1, k2, k3, k4, k5, k6, k7, k8 = Ji
            accs.append(
                (ax, ay, az, k0 * tx + k1 * ty + k2 * tz, k3 * tx + k4 * ty + k5 * tz, k6 * tx + k7 * ty + k8 * tz)
            )
        return pdots, accs

    def step(self, t: float, s: PlantState, u: np.ndarray | WrenchFunction, h: float) -> PlantState:
        """One RKMK4 step of length h (s). ``u`` is held (N,6) or evaluated per stage."""
        P0 = s.p.tolist()
        R0 = s.R.tolist()
        V0 = s.v.tolist()
        n = self.n
        if callable(u):

            def wrench(ts: float, P: list, Rf: list, V: list) -> list:
                st = PlantState(np.array(P), np.array(Rf).reshape(n, 3, 3), np.array(V))
                return self.saturate(np.asarray(u(ts, st), dtype=np.float64).tolist())
        else:
            U = self.saturate(np.asarray(u, dtype=np.float64).tolist())

            def wrench(ts: float, P: list, Rf: list, V: list) -> list:
                return U

        Rf0 = [r[0] + r[1] + r[2] for r in R0]
        p1, a1 = self._rates(t, P0, Rf0, V0, wrench(t, P0, Rf0, V0))
        K1 = [v[3:] for v in V0]

        def stage(c: float, pd, ac, K):
            th = [(c * k[0], c * k[1], c * k[2]) for k in K]
            P = [[p[0] + c * d[0], p[1] + c * d[1], p[2] + c * d[2]] for p, d in zip(P0, pd)]
            Rs = [_rot(R0[i], _exp(*th[i])) for i in range(n)]
            V = [[x + c * y for x, y in zip(v, a)] for v, a in zip(V0, ac)]
            return th, P, Rs, V

        half = 0.5 * h
        th2, P2, R2, V2 = stage(half, p1, a1, K1)
        p2, a2 = self._rates(t + half, P2, R2, V2, wrench(t + half, P2, R2, V2))
        K2 = [_dexpinv(*th2[i], *V2[i][3:]) for i in range(n)]
        th3, P3, R3, V3 = stage(half, p2, a2, K2)
        p3, a3 = self._rates(t + half, P3, R3, V3, wrench(t + half, P3, R3, V3))
        K3 = [_dexpinv(*th3[i], *V3[i][3:]) for i in range(n)]
        th4, P4, R4, V4 = stage(h, p3, a3, K3)
        p4, a4 = self._rates(t + h, P4, R4, V4, wrench(t + h, P4, R4, V4))
        K4 = [_dexpinv(*th4[i], *V4[i][3:]) for i in range(n)]
        w6 = h / 6.0
        P_new = []
        R_new = []
        V_new = []
        for i in range(n):
            P_new.append([P0[i][c] + w6 * (p1[i][c] + 2 * p2[i][c] + 2 * p3[i][c] + p4[i][c]) for c in range(3)])
            V_new.append([V0[i][c] + w6 * (a1[i][c] + 2 * a2[i][c] + 2 * a3[i][c] + a4[i][c]) for c in range(6)])
            k1, k2, k3, k4 = K1[i], K2[i], K3[i], K4[i]
            R_new.append(_rot(R0[i], _exp(*(w6 * (k1[c] + 2 * k2[c] + 2 * k3[c] + k4[c]) for c in range(3)))))
        return PlantState(np.array(P_new), np.array(R_new).reshape(n, 3, 3), np.array(V_new))
