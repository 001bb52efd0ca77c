"""One agent's prescribed-performance controller, from local measurements only.

The paper's Steps I–II (Section "Main Results"; docs/controller.md), one function per step
(:func:`formation_core.numba_kernels.formula`, compiled into :func:`agent_step`, the kernel):

- :func:`edge_errors`: e_k, ψ_k, e_Rk of an incident edge from the neighbour's relative pose;
- :func:`distance_term`, :func:`orientation_term`: ξ, the margin and the weight
  2 r_e ε_e / ρ_e or r_ψ / ρ_ψ of the edge in v_i,des;
- :func:`desired_velocity`: v_i,des (eq. vel_i_des), α = −I for the tail, R_k2ᵀR_k1 for the head;
- :func:`velocity_funnel_start`: ρ_v0 = 2|e_v(0)| + 1 or the file's value (docs/controller.md,
  "The velocity funnel's start");
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

import numpy as np

from formation_core import funnels
from formation_core.errors import FormationError
from formation_core.formation import AgentView
from formation_core.numba_kernels import formula, kernel
from formation_core.so3 import add3, flat_rows, matmul3, matrix_rows, matTvec3, matvec3, scale3, transpose3, vec3

OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = ("OK", "WARN", "ERROR")
#: Below this margin (fraction of a funnel left) the level is WARN.
WARN_MARGIN = 0.05
#: Why a step is at ERROR (column REASON of ``out``), and the message the agent reports.
REASON_NONE, REASON_SATURATED, REASON_NON_FINITE, REASON_MISSING = 0, 1, 2, 3
REASON_MESSAGES = ("", "outside a funnel: saturated", "non-finite wrench replaced by zero", "missing measurement")
#: Columns of ``edge_out`` (n_ends, 6): what a step leaves per edge end.
E, PSI, XI_E, XI_PSI, MARGIN_E, MARGIN_PSI = range(6)


class MissingMeasurementError(FormationError):
    """The relative pose of a tree neighbour is missing (out of sensing range or not received)."""

    def __init__(self, agent_id: str, neighbours: list[str]) -> None:
        self.neighbours = neighbours
        super().__init__(f"agent {agent_id}: no relative pose of neighbour(s) {', '.join(neighbours)}")


# Columns of the kernels' arrays: one float array per kind of row, so that a compiled call
# unboxes a handful of arrays (a few µs from Python), and a row is one agent's or one end's data.
#: ``ends`` (n_ends, END_COLUMNS): agent i's view of edge k (R_des row-major in 9 columns).
TAIL, D2, C_COL, C_CON, RHO_E_FLOOR, DECAY_E, RHO_PSI_0, RHO_PSI_INF, DECAY_PSI, R_DES = range(10)
END_COLUMNS = R_DES + 9
#: ``agents`` (N, AGENT_COLUMNS): gains, actuator limits and the velocity funnel (6 channels
#: each; RHO_V0 NaN for ``auto``). TAIL is 1.0 for the tail, 0.0 for the head; d2 = d_k,des² [m²];
#: RHO_E_FLOOR = ρ_e∞ / max(C_col, C_con); decays in 1/s; max force/torque inf for no limit.
DELTA, GAMMA, SATURATION_MARGIN, AUTO_SCALE, AUTO_OFFSET, MAX_FORCE, MAX_TORQUE, RHO_V0 = range(8)
RHO_V_INF, DECAY_V = RHO_V0 + 6, RHO_V0 + 12
AGENT_COLUMNS = DECAY_V + 6
#: ``start`` (N, 7): the velocity funnel's start, set at an agent's first step: t0 [s] (NaN
#: before) and ρ_v0 per channel.
T0, START_RHO_V0 = 0, 1
#: ``out`` (N, OUT_COLUMNS): what a step of agent i leaves: the wrench (body frame), v_des, ξ_v and
#: the velocity margins (6 each), the level (OK, WARN, ERROR) and the reason (REASON_*).
U, V_DES, XI_V, MARGIN_V, LEVEL, REASON = 0, 6, 12, 18, 24, 25
OUT_COLUMNS = 26


def new_outputs(n_agents: int, n_ends: int) -> tuple[np.ndarray, np.ndarray]:
    """Zeroed ``out`` (N, OUT_COLUMNS) and ``edge_out`` (n_ends, 6: E, PSI, XI_E, XI_PSI, MARGIN_E, MARGIN_PSI)."""
    return np.zeros((n_agents, OUT_COLUMNS)), np.zeros((n_ends, 6))


def new_funnel_start(n_agents: int) -> np.ndarray:
    """``start`` (N, 7) before any step: NaN."""
    return np.full((n_agents, 7), np.nan)


# --- the paper's steps -------------------------------------------------------------------------


@formula
def edge_errors(p_i_j_in_i, R_i_j, is_tail, d2, R_des):
    """Step I for edge k seen by agent i: (e_k, ψ_k, e_Rk) (eq. errors and eq. e_R_k and psi_k).

    In the tail's frame q = R_k1ᵀ(p_k2 − p_k1) and Q = R_k1ᵀR_k2: the tail measures them, the head
    measures R_k2ᵀ(p_k1 − p_k2) and R_k2ᵀR_k1 (docs/controller.md, "Signs and frames"). Then e = ‖q‖² − d² [m²],
    ψ = ½(3 − tr A) and e_R = S⁻¹(A − Aᵀ) with A = Q R_des. Vectors are 3-tuples, matrices row tuples.
    """
    if is_tail:
        q = p_i_j_in_i
        A = matmul3(R_i_j, R_des)
    else:
        q = scale3(-1.0, matTvec3(R_i_j, p_i_j_in_i))
        A = matmul3(transpose3(R_i_j), R_des)
    e = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] - d2
    psi = 0.5 * (3.0 - A[0][0] - A[1][1] - A[2][2])
    e_R = (A[2][1] - A[1][2], A[0][2] - A[2][0], A[1][0] - A[0][1])
    return e, psi, e_R


@formula
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


@formula
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


@formula
def alpha(R_i_j, is_tail, x):
    """α(i, k)·x (eq. vel_i_des): −x for the tail, R_k2ᵀR_k1 x = R_i_j x for the head."""
    if is_tail:
        return scale3(-1.0, x)
    return matvec3(R_i_j, x)


@formula
def desired_velocity(t, p_rel, R_rel, ends, lo, hi, delta, saturation_margin, edge_out):
    """v_i,des (eq. vel_i_des) from agent i's ends lo:hi, a 6-tuple; fills ``edge_out`` rows; (v_des, saturated).

    The distance part needs α(i,k)·R_k1ᵀ(p_k2 − p_k1), which is −p_i_j_in_i for either role
    (the paper's remark "Decentralized manner"): it is taken from the measurement directly.
    """
    v_lin = (0.0, 0.0, 0.0)
    v_ang = (0.0, 0.0, 0.0)
    saturated = False
    for k in range(lo, hi):
        g = ends[k]
        is_tail = g[TAIL] > 0.5
        p_i_j_in_i, R_i_j = vec3(p_rel[k]), matrix_rows(R_rel[k])
        e, psi, e_R = edge_errors(p_i_j_in_i, R_i_j, is_tail, g[D2], flat_rows(g, R_DES))
        xi_e, m_e, w_e, sat_e = distance_term(e, t, g[C_COL], g[C_CON], g[RHO_E_FLOOR], g[DECAY_E], saturation_margin)
        xi_psi, m_psi, w_psi, sat_psi = orientation_term(
            psi, t, g[RHO_PSI_0], g[RHO_PSI_INF], g[DECAY_PSI], saturation_margin
        )
        saturated = saturated or sat_e or sat_psi
        alpha_q = scale3(-1.0, p_i_j_in_i)
        v_lin = add3(v_lin, scale3(w_e, alpha_q))
        v_ang = add3(v_ang, scale3(w_psi, alpha(R_i_j, is_tail, e_R)))
        edge_out[k, E] = e
        edge_out[k, PSI] = psi
        edge_out[k, XI_E] = xi_e
        edge_out[k, XI_PSI] = xi_psi
        edge_out[k, MARGIN_E] = m_e
        edge_out[k, MARGIN_PSI] = m_psi
    v_lin = scale3(-delta, v_lin)
    v_ang = scale3(-delta, v_ang)
    return (v_lin[0], v_lin[1], v_lin[2], v_ang[0], v_ang[1], v_ang[2]), saturated


@formula
def velocity_funnel_start(e_v0, gains, start):
    """ρ_v0 per channel into ``start``: the file's value, or auto_scale·|e_v(0)| + auto_offset (Step II-a)."""
    for c in range(6):
        if np.isnan(gains[RHO_V0]):
            start[START_RHO_V0 + c] = gains[AUTO_SCALE] * abs(e_v0[c]) + gains[AUTO_OFFSET]
        else:
            start[START_RHO_V0 + c] = gains[RHO_V0 + c]


@formula
def wrench(t_since_start, e_v, gains, start, out):
    """u_i = −γ_i ρ_v⁻¹ r_v(ξ_v) T_v(ξ_v) per channel (eq. u_i) into ``out``; fills ξ_v and margins; saturated?"""
    saturated = False
    margin_sat = gains[SATURATION_MARGIN]
    keep = 1.0 - margin_sat
    for c in range(6):
        rho_v = funnels.rho(t_since_start, start[START_RHO_V0 + c], gains[RHO_V_INF + c], gains[DECAY_V + c])
        xi = e_v[c] / rho_v
        margin = funnels.margin_v(xi)
        out[XI_V + c] = xi
        out[MARGIN_V + c] = margin
        if margin < margin_sat:
            saturated = True
            xi = keep if xi > 0 else -keep
        out[U + c] = -gains[GAMMA] / rho_v * funnels.r_v(xi) * funnels.t_v(xi)
    return saturated


@formula
def limit_wrench(out, max_force, max_torque):
    """Scale the force and the torque in ``out`` down to their norms' limits, keeping directions."""
    for lo, limit in ((U, max_force), (U + 3, max_torque)):
        norm = np.sqrt(out[lo] * out[lo] + out[lo + 1] * out[lo + 1] + out[lo + 2] * out[lo + 2])
        if norm > limit:
            for c in range(lo, lo + 3):
                out[c] = out[c] * limit / norm


@formula
def fault_wrench(i, lo, hi, reason, out, edge_out, start):
    """The fault policy: zero wrench, level ERROR, margins −1 (unknown, treated as outside); before the
    agent's first step its velocity funnel has not started (``start[i, T0]`` NaN): its velocity margins
    are then +inf, nothing to judge (a link model's first sample may take a while to arrive)."""
    margin_v = np.inf if np.isnan(start[i, T0]) else -1.0
    for c in range(6):
        out[i, U + c] = 0.0
        out[i, V_DES + c] = 0.0
        out[i, XI_V + c] = 0.0
        out[i, MARGIN_V + c] = margin_v
    for k in range(lo, hi):
        for c in range(6):
            edge_out[k, c] = -1.0 if c == MARGIN_E or c == MARGIN_PSI else 0.0
    out[i, LEVEL] = ERROR
    out[i, REASON] = reason


@formula
def level_of(saturated, finite, out, edge_out, lo, hi):
    """(level, reason) of a step: ERROR when saturated or not finite, WARN near a bound, else OK."""
    if not finite:
        return ERROR, REASON_NON_FINITE
    if saturated:
        return ERROR, REASON_SATURATED
    worst = np.inf
    for c in range(6):
        worst = min(worst, out[MARGIN_V + c])
    for k in range(lo, hi):
        worst = min(worst, edge_out[k, MARGIN_E], edge_out[k, MARGIN_PSI])
    return (WARN if worst < WARN_MARGIN else OK), REASON_NONE


@kernel
def agent_step(t, i, lo, hi, p_rel, R_rel, v_measured, agents, ends, start, out, edge_out):
    """Agent i's whole step at time t [s] on its ends lo:hi: fills row i of ``out``; returns its level.

    ``p_rel``/``R_rel`` are indexed by edge end, ``v_measured`` is ṽ_i (6,). The velocity funnel
    starts at the agent's first step (row i of ``start`` is set then).
    """
    gains, row = agents[i], out[i]
    v_des, saturated = desired_velocity(t, p_rel, R_rel, ends, lo, hi, gains[DELTA], gains[SATURATION_MARGIN], edge_out)
    e_v = (
        v_measured[0] - v_des[0],
        v_measured[1] - v_des[1],
        v_measured[2] - v_des[2],
        v_measured[3] - v_des[3],
        v_measured[4] - v_des[4],
        v_measured[5] - v_des[5],
    )
    if np.isnan(start[i, T0]):
        start[i, T0] = t
        velocity_funnel_start(e_v, gains, start[i])
    saturated_v = wrench(t - start[i, T0], e_v, gains, start[i], row)
    limit_wrench(row, gains[MAX_FORCE], gains[MAX_TORQUE])
    finite = True
    for c in range(6):
        row[V_DES + c] = v_des[c]
        finite = finite and np.isfinite(row[U + c])
    if not finite:
        for c in range(6):
            row[U + c] = 0.0
    level, reason = level_of(saturated or saturated_v, finite, row, edge_out, lo, hi)
    row[LEVEL] = level
    row[REASON] = reason
    return level


# --- gains from a formation file -----------------------------------------------------------------


def gains(views: Sequence[AgentView]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernels' arrays for ``views`` (agents in this order, each with its incident edges):
    ``first_end`` (N+1,) (agent i owns ends first_end[i]:first_end[i+1]), ``agents``, ``ends``."""
    incident = [ie for v in views for ie in v.edges]
    first_end = np.cumsum([0] + [len(v.edges) for v in views]).astype(np.int64)
    ends = np.zeros((len(incident), END_COLUMNS))
    for row, ie in zip(ends, incident):
        edge = ie.edge
        row[TAIL] = ie.role == "tail"
        row[D2] = edge.d_des**2
        row[C_COL], row[C_CON] = edge.c_col, edge.c_con
        row[RHO_E_FLOOR] = funnels.rho_e_floor(edge.c_col, edge.c_con, edge.rho_e_inf)
        row[DECAY_E] = edge.decay_e
        row[RHO_PSI_0], row[RHO_PSI_INF], row[DECAY_PSI] = edge.rho_psi_0, edge.rho_psi_inf, edge.decay_psi
        row[R_DES : R_DES + 9] = np.asarray(edge.R_des, dtype=np.float64).ravel()
    agents = np.zeros((len(views), AGENT_COLUMNS))
    for row, view in zip(agents, views):
        c = view.controller
        f = c.velocity_funnel
        row[DELTA], row[GAMMA], row[SATURATION_MARGIN] = c.delta, c.gamma, c.saturation_margin
        row[AUTO_SCALE], row[AUTO_OFFSET] = f.auto_scale, f.auto_offset
        row[MAX_FORCE] = np.inf if c.max_force is None else c.max_force
        row[MAX_TORQUE] = np.inf if c.max_torque is None else c.max_torque
        row[RHO_V0 : RHO_V0 + 6] = np.nan if f.rho_0 is None else f.rho_0
        row[RHO_V_INF : RHO_V_INF + 6] = f.rho_inf
        row[DECAY_V : DECAY_V + 6] = f.decay
    return first_end, agents, ends


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


def control_output(
    t: float, i: int, lo: int, hi: int, out: np.ndarray, edge_out: np.ndarray, message: str | None = None
) -> ControlOutput:
    """Agent i's row of ``out`` and its ends lo:hi of ``edge_out`` as a :class:`ControlOutput`
    (``message`` overrides the reason's)."""
    row = out[i].tolist()
    edge = edge_out[lo:hi].T.tolist()
    level = int(row[LEVEL])
    if message is None and level == ERROR:
        message = REASON_MESSAGES[int(row[REASON])]
    elif message is None:
        message = "near a funnel bound" if level == WARN else ""
    return ControlOutput(
        t,
        tuple(row[U : U + 6]),
        tuple(row[V_DES : V_DES + 6]),
        tuple(edge[E]),
        tuple(edge[PSI]),
        tuple(edge[XI_E]),
        tuple(edge[XI_PSI]),
        tuple(edge[MARGIN_E]),
        tuple(edge[MARGIN_PSI]),
        tuple(row[XI_V : XI_V + 6]),
        tuple(row[MARGIN_V : MARGIN_V + 6]),
        level,
        message,
    )


class AgentController:
    """The controller of one agent (its process, a re-run, a rate analysis). Call :meth:`compute` per step.

    :meth:`compute` calls the compiled :func:`agent_step` on arrays built once (the gains, the
    funnel start, the outputs): its cost from Python is the dict of poses and the tuples of the
    :class:`ControlOutput`, not numba's dispatch.
    """

    def __init__(self, view: AgentView) -> None:
        self.view = view
        self.neighbours = tuple(ie.neighbour for ie in view.edges)
        _, self._agents, self._ends = gains([view])
        n = len(self.neighbours)
        self._out, self._edge_out = new_outputs(1, n)
        self._p = np.zeros((n, 3))
        self._R = np.zeros((n, 3, 3))
        self._start = new_funnel_start(1)

    @property
    def agent_id(self) -> str:
        return self.view.agent_id

    @property
    def rho_v0(self) -> tuple[float, ...] | None:
        """ρ_v0 per channel, set at the first step after a reset (None before)."""
        return None if self.t0 is None else tuple(self._start[0, START_RHO_V0:].tolist())

    @rho_v0.setter
    def rho_v0(self, value: Sequence[float] | None) -> None:
        self._start[0, START_RHO_V0:] = np.nan if value is None else value

    @property
    def t0(self) -> float | None:
        """Time [s] of the first step after a reset (None before): the velocity funnel's start."""
        t0 = float(self._start[0, T0])
        return None if np.isnan(t0) else t0

    @t0.setter
    def t0(self, value: float | None) -> None:
        self._start[0, T0] = np.nan if value is None else value

    def reset(self) -> None:
        """Forget the velocity funnel's start (ρ_v0 and t0 are set again at the next step)."""
        self._start[:] = np.nan

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
        n = len(self.neighbours)
        agent_step(
            float(t), 0, 0, n, self._p, self._R, v, self._agents, self._ends, self._start, self._out, self._edge_out
        )
        return control_output(float(t), 0, 0, n, self._out, self._edge_out)

    def fault_output(self, t: float, message: str) -> ControlOutput:
        """Zero wrench with level ERROR (missing, stale or non-finite measurements)."""
        n = len(self.neighbours)
        fault_wrench(0, 0, n, REASON_MISSING, self._out, self._edge_out, self._start)
        return control_output(float(t), 0, 0, n, self._out, self._edge_out, message)
