"""One agent's prescribed-performance controller, from local measurements only.

The paper's Steps I–II (Section "Main Results"; docs/controller.md), one compiled kernel per step:

- :func:`edge_errors`: e_k, ψ_k, e_Rk of an incident edge from the neighbour's relative pose;
- :func:`distance_term`, :func:`orientation_term`: ξ, the margin and the weight
  2 r_e ε_e / ρ_e or r_ψ / ρ_ψ of the edge in v_i,des;
- :func:`desired_velocity`: v_i,des (eq. vel_i_des), α = −I for the tail, R_k2ᵀR_k1 for the head;
- :func:`velocity_funnel_start`: ρ_v0 = 2|e_v(0)| + 1 (NOTES.md) or the file's value;
- :func:`wrench`: u_i = −γ_i ρ_v⁻¹ r_v(ξ_v) ε_v with e_v = ṽ_i − v_i,des (eq. u_i);
- :func:`limit_wrench`, :func:`fault_wrench`, :func:`agent_step`: actuator limits, the fault
  policy, and the whole step of agent i.

The kernels work on arrays over *edge ends*: every incident edge of every agent, grouped by
agent (agent i owns ends ``first_end[i]:first_end[i+1]``), so the run core steps every agent
of a formation with the same code an agent process runs for itself (:class:`AgentController`).

Inputs are what the topics carry (docs/topics.md): for neighbour j, ``p_i_j_in_i = R_iᵀ(p_j − p_i)``
[m] and ``R_i_j = R_iᵀ R_j``; the agent's own noisy body twist ṽ_i [m/s, rad/s]; the time t [s].
The wrench is in the body frame [N, N·m]. A normalised error outside its funnel (possible with a
sampled controller) is clamped to (1 − saturation_margin) of its domain: the wrench stays finite
and the level is ERROR. The wrench is bounded by design: its force and torque norms are scaled
down to the controller's ``max_force`` / ``max_torque`` (finite, at most the actuators' limits),
whatever the errors, so no measurement can make the controller command more than its actuators
can give.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from formation_msgs_py import funnels
from formation_msgs_py.compiled import kernel
from formation_msgs_py.errors import FormationError
from formation_msgs_py.so3 import add3, matTvec3, matvec3, scale3
from formation_msgs_py.spec import AgentView

OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = ("OK", "WARN", "ERROR")
#: Below this margin (fraction of a funnel left) the level is WARN.
WARN_MARGIN = 0.05
#: Why a step is at ERROR (``Outputs.reason``), and the message the agent reports.
REASON_NONE, REASON_SATURATED, REASON_NON_FINITE, REASON_MISSING = 0, 1, 2, 3
REASON_MESSAGES = ("", "outside a funnel: saturated", "non-finite wrench replaced by zero", "missing measurement")
#: Columns of ``Outputs.edge`` (per edge end).
E, PSI, XI_E, XI_PSI, MARGIN_E, MARGIN_PSI = range(6)


class MissingMeasurementError(FormationError):
    """The relative pose of a tree neighbour is missing (out of sensing range or not received)."""

    def __init__(self, agent_id: str, neighbours: list[str]) -> None:
        self.neighbours = neighbours
        super().__init__(f"agent {agent_id}: no relative pose of neighbour(s) {', '.join(neighbours)}")


class EdgeGains(NamedTuple):
    """Per edge end (agent i's view of edge k): role and funnel constants, arrays of length n_ends."""

    is_tail: np.ndarray  # bool
    d2: np.ndarray  # d_k,des² [m²]
    c_col: np.ndarray
    c_con: np.ndarray
    rho_e_floor: np.ndarray  # ρ_e∞ / max(C_col, C_con)
    decay_e: np.ndarray  # l_e [1/s]
    R_des: np.ndarray  # (n_ends, 3, 3)
    rho_psi_0: np.ndarray
    rho_psi_inf: np.ndarray
    decay_psi: np.ndarray  # l_ψ [1/s]


class AgentGains(NamedTuple):
    """Per agent: gains, velocity funnel and actuator limits, arrays of length N (or (N, 6))."""

    first_end: np.ndarray  # (N+1,) int: agent i owns ends first_end[i]:first_end[i+1]
    delta: np.ndarray
    gamma: np.ndarray
    saturation_margin: np.ndarray
    rho_v0: np.ndarray  # (N, 6): the file's ρ_v0, or NaN for ``auto``
    auto_scale: np.ndarray
    auto_offset: np.ndarray
    rho_v_inf: np.ndarray  # (N, 6)
    decay_v: np.ndarray  # (N, 6) [1/s]
    max_force: np.ndarray  # [N], inf: no limit
    max_torque: np.ndarray  # [N·m], inf: no limit


class Outputs(NamedTuple):
    """What a step of every agent leaves: filled by :func:`agent_step`."""

    u: np.ndarray  # (N, 6) wrench, body frame
    v_des: np.ndarray  # (N, 6)
    xi_v: np.ndarray  # (N, 6)
    margin_v: np.ndarray  # (N, 6)
    level: np.ndarray  # (N,) OK, WARN, ERROR
    reason: np.ndarray  # (N,) REASON_*
    edge: np.ndarray  # (n_ends, 6): e, ψ, ξ_e, ξ_ψ, margin_e, margin_ψ


class FunnelStart(NamedTuple):
    """Agent i's velocity funnel start, set at its first step: ρ_v0 (N, 6) and t0 (N,), NaN before."""

    rho_v0: np.ndarray
    t0: np.ndarray


def new_outputs(n_agents: int, n_ends: int) -> Outputs:
    return Outputs(
        np.zeros((n_agents, 6)),
        np.zeros((n_agents, 6)),
        np.zeros((n_agents, 6)),
        np.zeros((n_agents, 6)),
        np.zeros(n_agents, dtype=np.int64),
        np.zeros(n_agents, dtype=np.int64),
        np.zeros((n_ends, 6)),
    )


def new_funnel_start(n_agents: int) -> FunnelStart:
    return FunnelStart(np.full((n_agents, 6), np.nan), np.full(n_agents, np.nan))


# --- the paper's steps -------------------------------------------------------------------------


@kernel
def relative_entry(R_i_j, is_tail, a, b):
    """Entry (a, b) of Q = R_k1ᵀR_k2 from agent i's R_i_j: R_i_j for the tail, its transpose for the head."""
    return R_i_j[a, b] if is_tail else R_i_j[b, a]


@kernel
def offset_entry(R_i_j, is_tail, R_des, a, b):
    """Entry (a, b) of A = Q R_des, the relative orientation's offset from the desired one."""
    return (
        relative_entry(R_i_j, is_tail, a, 0) * R_des[0, b]
        + relative_entry(R_i_j, is_tail, a, 1) * R_des[1, b]
        + relative_entry(R_i_j, is_tail, a, 2) * R_des[2, b]
    )


@kernel
def edge_errors(p_i_j_in_i, R_i_j, is_tail, d2, R_des):
    """Step I for edge k seen by agent i: (e_k, ψ_k, e_Rk) (eq. errors and eq. e_R_k and psi_k).

    In the tail's frame q = R_k1ᵀ(p_k2 − p_k1) and Q = R_k1ᵀR_k2: the tail measures them, the head
    measures R_k2ᵀ(p_k1 − p_k2) and R_k2ᵀR_k1 (NOTES.md, conventions). Then e = ‖q‖² − d² [m²],
    ψ = ½(3 − tr A) and e_R = S⁻¹(A − Aᵀ) with A = Q R_des. e_R is a 3-tuple.
    """
    if is_tail:
        q = (p_i_j_in_i[0], p_i_j_in_i[1], p_i_j_in_i[2])
    else:
        q = scale3(-1.0, matTvec3(R_i_j, p_i_j_in_i))
    e = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] - d2
    a00 = offset_entry(R_i_j, is_tail, R_des, 0, 0)
    a11 = offset_entry(R_i_j, is_tail, R_des, 1, 1)
    a22 = offset_entry(R_i_j, is_tail, R_des, 2, 2)
    psi = 0.5 * (3.0 - a00 - a11 - a22)
    e_R = (
        offset_entry(R_i_j, is_tail, R_des, 2, 1) - offset_entry(R_i_j, is_tail, R_des, 1, 2),
        offset_entry(R_i_j, is_tail, R_des, 0, 2) - offset_entry(R_i_j, is_tail, R_des, 2, 0),
        offset_entry(R_i_j, is_tail, R_des, 1, 0) - offset_entry(R_i_j, is_tail, R_des, 0, 1),
    )
    return e, psi, e_R


@kernel
def distance_term(e, t, c_col, c_con, rho_e_floor, decay_e, saturation_margin):
    """Step I-a/b, distance: (ξ_e, margin, weight, saturated) with weight = 2 r_e(ξ_e) ε_e / ρ_e.

    Outside (or within ``saturation_margin`` of) the funnel ξ_e is clamped into (−C_col, C_con)
    before T_e and r_e (eq. ksi_k, epsilon errors).
    """
    rho_e = funnels.rho(t, 1.0, rho_e_floor, decay_e)
    xi = e / rho_e
    margin = funnels.margin_e(xi, c_col, c_con)
    x = xi
    saturated = margin < saturation_margin
    if saturated:
        keep = 1.0 - saturation_margin
        x = min(max(xi, -c_col * keep), c_con * keep)
    weight = 2.0 * funnels.r_e(x, c_col, c_con) / rho_e * funnels.t_e(x, c_col, c_con)
    return xi, margin, weight, saturated


@kernel
def orientation_term(psi, t, rho_psi_0, rho_psi_inf, decay_psi, saturation_margin):
    """Step I-a/b, orientation: (ξ_ψ, margin, weight, saturated) with weight = r_ψ(ξ_ψ) / ρ_ψ."""
    rho_psi = funnels.rho(t, rho_psi_0, rho_psi_inf, decay_psi)
    xi = psi / rho_psi
    margin = funnels.margin_psi(xi)
    x = xi
    saturated = margin < saturation_margin
    if saturated:
        x = 1.0 - saturation_margin
    return xi, margin, funnels.r_psi(max(x, 0.0)) / rho_psi, saturated


@kernel
def alpha(R_i_j, is_tail, x):
    """α(i, k)·x (eq. vel_i_des): −x for the tail, R_k2ᵀR_k1 x = R_i_j x for the head."""
    if is_tail:
        return scale3(-1.0, x)
    return matvec3(R_i_j, x)


@kernel
def desired_velocity(t, p_rel, R_rel, ends, lo, hi, delta, saturation_margin, edge_out):
    """v_i,des (eq. vel_i_des) from agent i's ends lo:hi, a 6-tuple; fills ``edge_out`` rows; (v_des, saturated).

    The distance part needs α(i,k)·R_k1ᵀ(p_k2 − p_k1), which is −p_i_j_in_i for either role
    (the paper's remark "Decentralized manner"): it is taken from the measurement directly.
    """
    v_lin = (0.0, 0.0, 0.0)
    v_ang = (0.0, 0.0, 0.0)
    saturated = False
    for k in range(lo, hi):
        e, psi, e_R = edge_errors(p_rel[k], R_rel[k], ends.is_tail[k], ends.d2[k], ends.R_des[k])
        xi_e, m_e, w_e, sat_e = distance_term(
            e, t, ends.c_col[k], ends.c_con[k], ends.rho_e_floor[k], ends.decay_e[k], saturation_margin
        )
        xi_psi, m_psi, w_psi, sat_psi = orientation_term(
            psi, t, ends.rho_psi_0[k], ends.rho_psi_inf[k], ends.decay_psi[k], saturation_margin
        )
        saturated = saturated or sat_e or sat_psi
        alpha_q = scale3(-1.0, p_rel[k])
        v_lin = add3(v_lin, scale3(w_e, alpha_q))
        v_ang = add3(v_ang, scale3(w_psi, alpha(R_rel[k], ends.is_tail[k], e_R)))
        edge_out[k, E] = e
        edge_out[k, PSI] = psi
        edge_out[k, XI_E] = xi_e
        edge_out[k, XI_PSI] = xi_psi
        edge_out[k, MARGIN_E] = m_e
        edge_out[k, MARGIN_PSI] = m_psi
    v_lin = scale3(-delta, v_lin)
    v_ang = scale3(-delta, v_ang)
    return (v_lin[0], v_lin[1], v_lin[2], v_ang[0], v_ang[1], v_ang[2]), saturated


@kernel
def velocity_funnel_start(e_v0, rho_v0_file, auto_scale, auto_offset, rho_v0):
    """ρ_v0 per channel into ``rho_v0``: the file's value, or auto_scale·|e_v(0)| + auto_offset (Step II-a)."""
    for c in range(6):
        rho_v0[c] = auto_scale * abs(e_v0[c]) + auto_offset if np.isnan(rho_v0_file[0]) else rho_v0_file[c]


@kernel
def wrench(t_since_start, e_v, rho_v0, rho_v_inf, decay_v, gamma, saturation_margin, u, xi_out, margin_out):
    """u_i = −γ_i ρ_v⁻¹ r_v(ξ_v) T_v(ξ_v) per channel (eq. u_i) into ``u``; fills ξ_v and margins; saturated?"""
    saturated = False
    keep = 1.0 - saturation_margin
    for c in range(6):
        rho_v = funnels.rho(t_since_start, rho_v0[c], rho_v_inf[c], decay_v[c])
        xi = e_v[c] / rho_v
        margin = funnels.margin_v(xi)
        xi_out[c] = xi
        margin_out[c] = margin
        if margin < saturation_margin:
            saturated = True
            xi = keep if xi > 0 else -keep
        u[c] = -gamma / rho_v * funnels.r_v(xi) * funnels.t_v(xi)
    return saturated


@kernel
def limit_wrench(u, max_force, max_torque):
    """Scale the force and the torque down to their norms' limits, keeping directions (in place)."""
    for lo, limit in ((0, max_force), (3, max_torque)):
        norm = np.sqrt(u[lo] ** 2 + u[lo + 1] ** 2 + u[lo + 2] ** 2)
        if norm > limit:
            for c in range(lo, lo + 3):
                u[c] = u[c] * limit / norm


@kernel
def all_finite(x):
    for c in range(x.shape[0]):
        if not np.isfinite(x[c]):
            return False
    return True


@kernel
def fault_wrench(i, lo, hi, reason, out):
    """The fault policy: zero wrench, level ERROR, margins −1 (unknown, treated as outside)."""
    out.u[i, :] = 0.0
    out.v_des[i, :] = 0.0
    out.xi_v[i, :] = 0.0
    out.margin_v[i, :] = -1.0
    out.edge[lo:hi, :] = 0.0
    out.edge[lo:hi, MARGIN_E] = -1.0
    out.edge[lo:hi, MARGIN_PSI] = -1.0
    out.level[i] = ERROR
    out.reason[i] = reason


@kernel
def agent_step(t, i, p_rel, R_rel, v_measured, agents, ends, start, out):
    """Agent i's whole step at time t [s]: fills row i of ``out``; returns its level.

    ``p_rel``/``R_rel`` are indexed by edge end (agent i reads ends first_end[i]:first_end[i+1]).
    The velocity funnel starts at the agent's first step (``start`` is updated then).
    """
    lo, hi = agents.first_end[i], agents.first_end[i + 1]
    margin = agents.saturation_margin[i]
    v_des, saturated = desired_velocity(t, p_rel, R_rel, ends, lo, hi, agents.delta[i], margin, out.edge)
    e_v = (
        v_measured[0] - v_des[0],
        v_measured[1] - v_des[1],
        v_measured[2] - v_des[2],
        v_measured[3] - v_des[3],
        v_measured[4] - v_des[4],
        v_measured[5] - v_des[5],
    )
    if np.isnan(start.t0[i]):
        start.t0[i] = t
        velocity_funnel_start(e_v, agents.rho_v0[i], agents.auto_scale[i], agents.auto_offset[i], start.rho_v0[i])
    u = out.u[i]
    sat_v = wrench(
        t - start.t0[i],
        e_v,
        start.rho_v0[i],
        agents.rho_v_inf[i],
        agents.decay_v[i],
        agents.gamma[i],
        margin,
        u,
        out.xi_v[i],
        out.margin_v[i],
    )
    limit_wrench(u, agents.max_force[i], agents.max_torque[i])
    for c in range(6):
        out.v_des[i, c] = v_des[c]
    out.reason[i] = REASON_NONE
    if not all_finite(u):
        u[:] = 0.0
        out.level[i] = ERROR
        out.reason[i] = REASON_NON_FINITE
    elif saturated or sat_v:
        out.level[i] = ERROR
        out.reason[i] = REASON_SATURATED
    elif min(out.margin_v[i].min(), out.edge[lo:hi, MARGIN_E].min(), out.edge[lo:hi, MARGIN_PSI].min()) < WARN_MARGIN:
        out.level[i] = WARN
    else:
        out.level[i] = OK
    return out.level[i]


# --- gains from a formation file -----------------------------------------------------------------


def gains(views: Sequence[AgentView]) -> tuple[AgentGains, EdgeGains]:
    """The kernels' arrays for ``views`` (agents in this order, each with its incident edges)."""
    ends = [ie for v in views for ie in v.edges]
    first_end = np.cumsum([0] + [len(v.edges) for v in views])

    def per_end(f) -> np.ndarray:
        return np.array([f(ie) for ie in ends], dtype=np.float64)

    edge_gains = EdgeGains(
        np.array([ie.role == "tail" for ie in ends], dtype=np.bool_),
        per_end(lambda ie: ie.edge.d_des**2),
        per_end(lambda ie: ie.edge.c_col),
        per_end(lambda ie: ie.edge.c_con),
        per_end(lambda ie: funnels.rho_e_floor(ie.edge.c_col, ie.edge.c_con, ie.edge.rho_e_inf)),
        per_end(lambda ie: ie.edge.decay_e),
        np.array([ie.edge.R_des for ie in ends], dtype=np.float64).reshape(len(ends), 3, 3),
        per_end(lambda ie: ie.edge.rho_psi_0),
        per_end(lambda ie: ie.edge.rho_psi_inf),
        per_end(lambda ie: ie.edge.decay_psi),
    )
    ctl = [v.controller for v in views]
    vf = [c.velocity_funnel for c in ctl]
    inf = np.inf
    agent_gains = AgentGains(
        first_end.astype(np.int64),
        np.array([c.delta for c in ctl], dtype=np.float64),
        np.array([c.gamma for c in ctl], dtype=np.float64),
        np.array([c.saturation_margin for c in ctl], dtype=np.float64),
        np.array([np.full(6, np.nan) if f.rho_0 is None else f.rho_0 for f in vf], dtype=np.float64).reshape(-1, 6),
        np.array([f.auto_scale for f in vf], dtype=np.float64),
        np.array([f.auto_offset for f in vf], dtype=np.float64),
        np.array([f.rho_inf for f in vf], dtype=np.float64).reshape(-1, 6),
        np.array([f.decay for f in vf], dtype=np.float64).reshape(-1, 6),
        np.array([inf if c.max_force is None else c.max_force for c in ctl], dtype=np.float64),
        np.array([inf if c.max_torque is None else c.max_torque for c in ctl], dtype=np.float64),
    )
    return agent_gains, edge_gains


# --- one agent, as its process runs it -----------------------------------------------------------


@dataclass(frozen=True)
class ControlOutput:
    """The wrench and what the agent knows of its funnels at time ``t``.

    Tuples of floats. Per-edge entries follow ``AgentView.edges``; velocity entries are
    [vx, vy, vz, wx, wy, wz].
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


def control_output(t: float, i: int, lo: int, hi: int, out: Outputs, message: str | None = None) -> ControlOutput:
    """Agent i's row of ``out`` as a :class:`ControlOutput` (``message`` overrides the reason's)."""
    edge = out.edge[lo:hi].T.tolist()
    level = int(out.level[i])
    if message is None:
        message = REASON_MESSAGES[out.reason[i]] if level == ERROR else ("near a funnel bound" if level == WARN else "")
    return ControlOutput(
        t,
        tuple(out.u[i].tolist()),
        tuple(out.v_des[i].tolist()),
        tuple(edge[E]),
        tuple(edge[PSI]),
        tuple(edge[XI_E]),
        tuple(edge[XI_PSI]),
        tuple(edge[MARGIN_E]),
        tuple(edge[MARGIN_PSI]),
        tuple(out.xi_v[i].tolist()),
        tuple(out.margin_v[i].tolist()),
        level,
        message,
    )


class AgentController:
    """The controller of one agent (its process, a re-run, a rate analysis). Call :meth:`compute` per step."""

    def __init__(self, view: AgentView) -> None:
        self.view = view
        self.neighbours = tuple(ie.neighbour for ie in view.edges)
        self._agents, self._ends = gains([view])
        n = len(self.neighbours)
        self._out = new_outputs(1, n)
        self._p = np.zeros((n, 3))
        self._R = np.zeros((n, 3, 3))
        self.reset()

    @property
    def agent_id(self) -> str:
        return self.view.agent_id

    @property
    def rho_v0(self) -> tuple[float, ...] | None:
        """ρ_v0 per channel, set at the first step after a reset (None before)."""
        return None if np.isnan(self._start.t0[0]) else tuple(self._start.rho_v0[0].tolist())

    @rho_v0.setter
    def rho_v0(self, value: Sequence[float] | None) -> None:
        self._start.rho_v0[0] = np.nan if value is None else value

    @property
    def t0(self) -> float | None:
        """Time [s] of the first step after a reset (None before): the velocity funnel's start."""
        return None if np.isnan(self._start.t0[0]) else float(self._start.t0[0])

    @t0.setter
    def t0(self, value: float | None) -> None:
        self._start.t0[0] = np.nan if value is None else value

    def reset(self) -> None:
        """Forget the velocity funnel's start (ρ_v0 and t0 are set again at the next step)."""
        self._start = new_funnel_start(1)

    def compute(
        self,
        t: float,
        relative_poses: Mapping[str, tuple[Sequence[float], Sequence[Sequence[float]]]],
        v_measured: Sequence[float],
    ) -> ControlOutput:
        """Wrench at time t (s) from ``{neighbour: (p_i_j_in_i, R_i_j)}`` and ṽ_i (body frame)."""
        missing = [j for j in self.neighbours if j not in relative_poses]
        if missing:
            raise MissingMeasurementError(self.view.agent_id, missing)
        for k, j in enumerate(self.neighbours):
            p, R = relative_poses[j]
            self._p[k] = p
            self._R[k] = R
        v = np.asarray(v_measured, dtype=np.float64)
        agent_step(float(t), 0, self._p, self._R, v, self._agents, self._ends, self._start, self._out)
        return control_output(float(t), 0, 0, len(self.neighbours), self._out)

    def fault_output(self, t: float, message: str) -> ControlOutput:
        """Zero wrench with level ERROR (missing, stale or non-finite measurements)."""
        fault_wrench(0, 0, len(self.neighbours), REASON_MISSING, self._out)
        return control_output(float(t), 0, 0, len(self.neighbours), self._out, message)
