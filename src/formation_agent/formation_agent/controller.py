"""One agent's prescribed-performance controller, from local measurements only.

Implements the paper's Steps I-II (docs/controller.md) for agent i:

- per incident edge k = (k1, k2): e_k, ψ_k, e_Rk from the neighbour's relative pose;
- the desired velocity v_i,des (eq. vel_i_des), α = −I for the tail, R_k2ᵀR_k1 for the head;
- the wrench u_i = −γ_i ρ_v⁻¹ r_v(ξ_v) ε_v with e_v = ṽ_i − v_i,des.

Inputs are what the topics carry (docs/topics.md): for neighbour j, ``p_i_j_in_i = R_iᵀ(p_j − p_i)``
(m) and ``R_i_j = R_iᵀ R_j``; the agent's own noisy body twist ṽ_i [m/s, rad/s]; the time t (s).
The output wrench is in the body frame [N, N·m].

A normalised error outside its funnel (possible with a sampled controller) is clamped to
(1 − saturation_margin) of its domain: the wrench stays finite and the level is ERROR. The
wrench is bounded by design: its force and torque norms are scaled down to the controller's
``max_force`` / ``max_torque`` (finite, at most the actuators' limits), whatever the errors,
so no measurement can make the controller command more than its actuators can give.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from formation_msgs_py.errors import FormationError
from formation_msgs_py.spec import AgentView

OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = ("OK", "WARN", "ERROR")
#: Below this margin (fraction of a funnel left) the level is WARN.
WARN_MARGIN = 0.05


class MissingMeasurementError(FormationError):
    """The relative pose of a tree neighbour is missing (out of sensing range or not received)."""

    def __init__(self, agent_id: str, neighbours: list[str]) -> None:
        self.neighbours = neighbours
        super().__init__(f"agent {agent_id}: no relative pose of neighbour(s) {', '.join(neighbours)}")


@dataclass(frozen=True)
class ControlOutput:
    """The wrench and what the agent knows of its funnels at time ``t``.

    Tuples of floats (cheaper than small numpy arrays in the control loop). Per-edge entries
    follow ``AgentView.edges``; velocity entries are [vx, vy, vz, wx, wy, wz].
    """

    t: float
    wrench: tuple[float, ...]
    v_des: tuple[float, ...]
    e: tuple[float, ...]
    psi: tuple[float, ...]
    xi_e: tuple[float, ...]
    xi_psi: tuple[float, ...]
    margin_e: tuple[float, ...]
    margin_psi: tuple[float, ...]
    xi_v: tuple[float, ...]
    margin_v: tuple[float, ...]
    level: int
    message: str

    @property
    def min_margin(self) -> float:
        """Smallest margin over every edge and velocity channel (1 = centre, <0 = outside)."""
        return min(self.margin_v + self.margin_e + self.margin_psi)


class AgentController:
    """The controller of one agent. Call :meth:`compute` once per control step.

    Written with Python floats rather than numpy: for 3- and 6-vectors the interpreter is
    several times faster than numpy's per-call overhead, and this runs at several kHz.
    """

    def __init__(self, view: AgentView) -> None:
        self.view = view
        g = view.controller
        self._delta = g.delta
        self._gamma = g.gamma
        self._margin = g.saturation_margin
        vf = g.velocity_funnel
        self._rho_v0_fixed = None if vf.rho_0 is None else tuple(vf.rho_0)
        self._auto_scale = vf.auto_scale
        self._auto_offset = vf.auto_offset
        self._rho_v_inf = tuple(vf.rho_inf)
        self._decay_v = tuple(vf.decay)
        self._max_force = g.max_force
        self._max_torque = g.max_torque
        # per edge: neighbour, is_tail, d², C_col, C_con, ρ_e∞/C_max, l_e, R_des (9, row-major),
        # ρ_ψ0, ρ_ψ∞, l_ψ
        self._edges = [
            (
                ie.neighbour,
                ie.role == "tail",
                ie.edge.d_des**2,
                ie.edge.c_col,
                ie.edge.c_con,
                ie.edge.rho_e_inf / max(ie.edge.c_col, ie.edge.c_con),
                ie.edge.decay_e,
                tuple(float(x) for x in ie.edge.R_des.ravel()),
                ie.edge.rho_psi_0,
                ie.edge.rho_psi_inf,
                ie.edge.decay_psi,
            )
            for ie in view.edges
        ]
        self.reset()

    @property
    def agent_id(self) -> str:
        return self.view.agent_id

    def reset(self) -> None:
        """Forget the velocity funnel's start (ρ_v0 and t0 are set again at the next step)."""
        self.rho_v0: tuple[float, ...] | None = None
        self.t0: float | None = None

    def compute(
        self,
        t: float,
        relative_poses: Mapping[str, tuple[Sequence[float], Sequence[Sequence[float]]]],
        v_measured: Sequence[float],
    ) -> ControlOutput:
        """Wrench at time t (s) from ``{neighbour: (p_i_j_in_i, R_i_j)}`` and ṽ_i (body frame).

        ``p_i_j_in_i`` is a 3-vector and ``R_i_j`` a 3×3 rotation (numpy arrays or sequences).
        """
        missing = [e[0] for e in self._edges if e[0] not in relative_poses]
        if missing:
            raise MissingMeasurementError(self.view.agent_id, missing)
        exp = math.exp
        log = math.log
        margin = self._margin
        keep = 1.0 - margin
        saturated = False
        lx = ly = lz = ax = ay = az = 0.0
        es, psis, xies, xipsis, mes, mpsis = [], [], [], [], [], []
        for j, is_tail, d2, c_col, c_con, floor, l_e, Rd, rp0, rpi, l_psi in self._edges:
            p_raw, R_raw = relative_poses[j]
            if not isinstance(p_raw, (list, tuple)):  # numpy: floats are faster than np.float64
                p_raw = p_raw.tolist()
                R_raw = R_raw.tolist()
            px, py, pz = p_raw
            (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R_raw
            # Canonical edge quantities in the tail's frame: q = R_k1ᵀ(p_k2 − p_k1), Q = R_k1ᵀR_k2.
            # α·q is −q for the tail and R_k2ᵀ(p_k2 − p_k1) = −p_i_j_in_i for the head.
            if is_tail:
                qx, qy, qz = px, py, pz
                q00, q01, q02, q10, q11, q12, q20, q21, q22 = r00, r01, r02, r10, r11, r12, r20, r21, r22
                aqx, aqy, aqz = -px, -py, -pz
            else:
                q00, q01, q02, q10, q11, q12, q20, q21, q22 = r00, r10, r20, r01, r11, r21, r02, r12, r22
                qx = -(q00 * px + q01 * py + q02 * pz)
                qy = -(q10 * px + q11 * py + q12 * pz)
                qz = -(q20 * px + q21 * py + q22 * pz)
                aqx, aqy, aqz = -px, -py, -pz
            e = qx * qx + qy * qy + qz * qz - d2
            d00, d01, d02, d10, d11, d12, d20, d21, d22 = Rd
            # A = Q R_des; ψ = ½(3 − tr A); e_R = S⁻¹(A − Aᵀ)
            a00 = q00 * d00 + q01 * d10 + q02 * d20
            a11 = q10 * d01 + q11 * d11 + q12 * d21
            a22 = q20 * d02 + q21 * d12 + q22 * d22
            a01 = q00 * d01 + q01 * d11 + q02 * d21
            a02 = q00 * d02 + q01 * d12 + q02 * d22
            a10 = q10 * d00 + q11 * d10 + q12 * d20
            a12 = q10 * d02 + q11 * d12 + q12 * d22
            a20 = q20 * d00 + q21 * d10 + q22 * d20
            a21 = q20 * d01 + q21 * d11 + q22 * d21
            psi = 0.5 * (3.0 - a00 - a11 - a22)
            ex, ey, ez = a21 - a12, a02 - a20, a10 - a01
            if is_tail:
                aex, aey, aez = -ex, -ey, -ez
            else:  # α = R_k2ᵀR_k1 = R_i_j
                aex = r00 * ex + r01 * ey + r02 * ez
                aey = r10 * ex + r11 * ey + r12 * ez
                aez = r20 * ex + r21 * ey + r22 * ez
            # distance channel
            rho_e = (1.0 - floor) * exp(-l_e * t) + floor
            xi_e = e / rho_e
            me = min(1.0 + xi_e / c_col, 1.0 - xi_e / c_con)
            xi = xi_e
            if me < margin:
                saturated = True
                xi = min(max(xi, -c_col * keep), c_con * keep)
            gain = (
                2.0 * (1.0 / (c_col + xi) + 1.0 / (c_con - xi)) / rho_e * log((1.0 + xi / c_col) / (1.0 - xi / c_con))
            )
            lx += gain * aqx
            ly += gain * aqy
            lz += gain * aqz
            # orientation channel
            rho_psi = (rp0 - rpi) * exp(-l_psi * t) + rpi
            xi_psi = psi / rho_psi
            mpsi = 1.0 - xi_psi
            xi = xi_psi
            if mpsi < margin:
                saturated = True
                xi = keep
            gain = 1.0 / ((1.0 - max(xi, 0.0)) * rho_psi)
            ax += gain * aex
            ay += gain * aey
            az += gain * aez
            es.append(e)
            psis.append(psi)
            xies.append(xi_e)
            xipsis.append(xi_psi)
            mes.append(me)
            mpsis.append(mpsi)
        dl = -self._delta
        v_des = (dl * lx, dl * ly, dl * lz, dl * ax, dl * ay, dl * az)
        if not isinstance(v_measured, (list, tuple)):
            v_measured = v_measured.tolist()
        e_v = [vm - vd for vm, vd in zip(v_measured, v_des)]
        if self.rho_v0 is None:
            self.t0 = t
            if self._rho_v0_fixed is None:
                self.rho_v0 = tuple(self._auto_scale * abs(x) + self._auto_offset for x in e_v)
            else:
                self.rho_v0 = self._rho_v0_fixed
        dt = t - self.t0
        gamma = self._gamma
        u = []
        xi_v = []
        m_v = []
        for ev, r0, rinf, lv in zip(e_v, self.rho_v0, self._rho_v_inf, self._decay_v):
            rho = (r0 - rinf) * exp(-lv * dt) + rinf
            x = ev / rho
            m = 1.0 - abs(x)
            xi_v.append(x)
            m_v.append(m)
            if m < margin:
                saturated = True
                x = keep if x > 0 else -keep
            u.append(-gamma / rho * (2.0 / (1.0 - x * x)) * log((1.0 + x) / (1.0 - x)))
        u = self._limit(u)
        message = ""
        if saturated or not all(math.isfinite(x) for x in u):
            level = ERROR
            message = "outside a funnel: saturated"
            if not all(math.isfinite(x) for x in u):
                u = [0.0] * 6
                message = "non-finite wrench replaced by zero"
        elif min(m_v + mes + mpsis) < WARN_MARGIN:
            level = WARN
            message = "near a funnel bound"
        else:
            level = OK
        return ControlOutput(
            t,
            tuple(u),
            v_des,
            tuple(es),
            tuple(psis),
            tuple(xies),
            tuple(xipsis),
            tuple(mes),
            tuple(mpsis),
            tuple(xi_v),
            tuple(m_v),
            level,
            message,
        )

    def _limit(self, u: list[float]) -> list[float]:
        """Force and torque scaled down to their norm limits (direction kept)."""
        for lo, limit in ((0, self._max_force), (3, self._max_torque)):
            norm = math.sqrt(u[lo] ** 2 + u[lo + 1] ** 2 + u[lo + 2] ** 2)
            if norm > limit:
                u[lo : lo + 3] = [x * limit / norm for x in u[lo : lo + 3]]
        return u

    def fault_output(self, t: float, message: str) -> ControlOutput:
        """Zero wrench with level ERROR (missing, stale or non-finite measurements).

        Margins are reported as −1 (unknown, treated as outside).
        """
        n = len(self._edges)
        zeros = (0.0,) * n
        return ControlOutput(
            t,
            (0.0,) * 6,
            (0.0,) * 6,
            zeros,
            zeros,
            zeros,
            zeros,
            (-1.0,) * n,
            (-1.0,) * n,
            (0.0,) * 6,
            (-1.0,) * 6,
            ERROR,
            message,
        )
