"""How far two correct computations of one controller step can be apart: a round-off bound.

Two processes that run :func:`formation_agent.controller.agent_step` on the same inputs give the
same bits when they run the same machine code with the same libraries (the simulator's witness
then asks for equality). On another CPU, with another libm or SIMD path, or interpreted instead of
compiled, every operation may round differently, and the controller amplifies those differences:
the wrench's sensitivity to the velocity error grows like γ·r_v'(ξ_v)/ρ_v², i.e. 4γ/ρ_v² at the
centre of a funnel that shrinks over the run. This module bounds that difference, step by step,
along the controller's own steps (docs/controller.md, "How far two correct answers can be apart").

The bound is a first-order running error analysis. Every basic operation rounds with a relative
error of at most :data:`UNIT` (2⁻⁵³, IEEE double); ``exp`` and ``log`` are trusted to
:data:`KAPPA`·UNIT (4 units in the last place, more than any libm or numpy SIMD path in use
claims). For each quantity x of :func:`agent_step` (q, e, ψ, e_R, ρ, ξ, the weights, v_des, e_v,
ρ_v, ξ_v, u) a bound Δx on |x̂ − x| is carried forward with the rules

    Δ(a ± b) = Δa + Δb + UNIT·|a ± b|,    Δ(a·b) = |b|Δa + |a|Δb + UNIT·|a·b|,
    Δf(x) = |f'(x*)|·Δx + (rounding of f at x),

where f' is taken at the worst point x* within Δx of x inside the funnel (the clamp of a saturated
error included). Two computations that each lie within Δ of the exact value are within 2Δ of
each other; :data:`SAFETY` doubles that again for the second-order terms the analysis drops, so
the tolerance of a comparison is ``2·SAFETY·Δ`` (:func:`tolerance`).

State: an agent's velocity funnel starts at its first step with ρ_v0 = auto_scale·|e_v(0)| +
auto_offset, so two computations may carry slightly different ρ_v0 for the rest of the run; the
bound of that difference is kept in ``rho_v0_bound`` (N, 6), NaN until the agent's first step.

Bounds are written in the layout of the controller's outputs: ``bound_out`` (N, OUT_COLUMNS) at
U, V_DES, XI_V and MARGIN_V, and ``bound_edge`` (n_ends, 6) for E, PSI, XI_E, XI_PSI, MARGIN_E,
MARGIN_PSI, so that a test or the witness compares each output with its own bound.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from formation_agent.controller import (
    AUTO_SCALE,
    C_COL,
    C_CON,
    D2,
    DECAY_E,
    DECAY_PSI,
    DECAY_V,
    DELTA,
    GAMMA,
    MARGIN_E,
    MARGIN_PSI,
    MARGIN_V,
    MAX_FORCE,
    MAX_TORQUE,
    PSI,
    R_DES,
    REASON,
    REASON_NON_FINITE,
    RHO_E_FLOOR,
    RHO_PSI_0,
    RHO_PSI_INF,
    RHO_V0,
    RHO_V_INF,
    SATURATION_MARGIN,
    START_RHO_V0,
    T0,
    TAIL,
    V_DES,
    XI_E,
    XI_PSI,
    XI_V,
    AgentController,
    ControlOutput,
    E,
    U,
    edge_errors,
    new_outputs,
)
from formation_core import funnels
from formation_core.formation import AgentView
from formation_core.numba_kernels import formula, kernel
from formation_core.so3 import flat_rows, matrix_rows, vec3

#: unit round-off of IEEE double: the largest relative error of one correctly rounded operation
UNIT = 2.0**-53
#: relative error allowed of exp and log, in units of UNIT: 4 ulp (glibc claims < 1 ulp, numpy's
#: SIMD paths a few; the bound must hold for any libm an agent's host may have)
KAPPA = 8.0
#: room for the second-order terms a first-order analysis leaves out
SAFETY = 2.0


def tolerance(bound: np.ndarray | float) -> np.ndarray | float:
    """The largest difference between two correct computations whose outputs each carry ``bound``:
    both within the bound of the exact value (2×), and :data:`SAFETY` for the second order."""
    return 2.0 * SAFETY * bound


@formula
def rho_bound(t, rho_0, rho_inf, decay, rho_value):
    """Δρ of ρ(t) = (ρ0 − ρ∞)·exp(−l·t) + ρ∞ as :func:`formation_core.funnels.rho` computes it:
    the argument −l·t (two roundings when t is a difference), exp, one product and one sum."""
    return UNIT * (abs(rho_0 - rho_inf) * np.exp(-decay * t) * (2.0 * decay * t + KAPPA + 3.0) + 2.0 * abs(rho_value))


@formula
def clamp(x, lo, hi):
    return min(max(x, lo), hi)


@formula
def distance_weight_slope(x, c_col, c_con):
    """|d/dx (r_e(x)·T_e(x))| = |r_e'·T_e + r_e²| (the weight 2 r_e T_e / ρ_e, per unit of ξ_e)."""
    r = funnels.r_e(x, c_col, c_con)
    r_slope = -1.0 / ((c_col + x) * (c_col + x)) + 1.0 / ((c_con - x) * (c_con - x))
    return abs(r_slope * funnels.t_e(x, c_col, c_con) + r * r)


@formula
def distance_bounds(e, de, t, c_col, c_con, floor, decay, saturation_margin):
    """(Δξ_e, Δw_e, w_e) of :func:`formation_agent.controller.distance_term` given e and its bound Δe."""
    rho = funnels.rho(t, 1.0, floor, decay)
    drho = rho_bound(t, 1.0, floor, decay, rho)
    xi = e / rho
    dxi = de / rho + abs(xi) * drho / rho + UNIT * abs(xi)
    keep = 1.0 - saturation_margin
    lo, hi = -c_col * keep, c_con * keep
    x = xi
    if funnels.margin_e(xi, c_col, c_con) < saturation_margin:
        x = clamp(xi, lo, hi)
    slope = max(
        distance_weight_slope(clamp(x - dxi, lo, hi), c_col, c_con),
        distance_weight_slope(x, c_col, c_con),
        distance_weight_slope(clamp(x + dxi, lo, hi), c_col, c_con),
    )
    r = funnels.r_e(x, c_col, c_con)
    T = funnels.t_e(x, c_col, c_con)
    w = 2.0 * r / rho * T
    # rounding of r_e and T_e at x: the sums c + x lose relative accuracy near the funnel's bounds
    rel_r = 3.0 * UNIT + UNIT * (c_col + abs(x)) / (c_col + x) + UNIT * (c_con + abs(x)) / (c_con - x)
    rel_y = (
        5.0 * UNIT
        + UNIT * (1.0 + abs(x) / c_col) / (1.0 + x / c_col)
        + UNIT * (1.0 + abs(x) / c_con) / (1.0 - x / c_con)
    )
    dT = rel_y + KAPPA * UNIT * abs(T)
    dw = 2.0 / rho * (slope * dxi + abs(T) * r * rel_r + r * dT) + abs(w) * (drho / rho + 3.0 * UNIT)
    return dxi, dw, w


@formula
def orientation_bounds(psi, dpsi, t, rho_0, rho_inf, decay, saturation_margin):
    """(Δξ_ψ, Δw_ψ, w_ψ) of :func:`formation_agent.controller.orientation_term` given ψ and Δψ."""
    rho = funnels.rho(t, rho_0, rho_inf, decay)
    drho = rho_bound(t, rho_0, rho_inf, decay, rho)
    xi = psi / rho
    dxi = dpsi / rho + abs(xi) * drho / rho + UNIT * abs(xi)
    keep = 1.0 - saturation_margin
    x = xi
    if funnels.margin_psi(xi) < saturation_margin:
        x = keep
    x = max(x, 0.0)
    worst = min(x + dxi, keep)  # r_ψ' = 1/(1 − x)² grows with x
    w = funnels.r_psi(x) / rho
    dw = dxi / ((1.0 - worst) * (1.0 - worst) * rho) + abs(w) * (drho / rho + UNIT * (1.0 + x) / (1.0 - x) + 3.0 * UNIT)
    return dxi, dw, w


@formula
def velocity_wrench_slope(x):
    """d/dx (r_v(x)·T_v(x)) = r_v'·T_v + r_v² at x ≥ 0 (even in x): the wrench per unit of ξ_v, over γ/ρ_v."""
    s = 1.0 - x * x
    return 4.0 * x / (s * s) * funnels.t_v(x) + 4.0 / (s * s)


@formula
def end_bounds(p_rel, R_rel, g, k, t, saturation_margin, bound_edge, work):
    """Bounds of edge end k's outputs into ``bound_edge[k]``; adds the bounds of its terms of
    v_lin and v_ang (before the factor −δ) into ``work[DV]`` and their sizes into ``work[SIZES]``."""
    is_tail = g[TAIL] > 0.5
    p, R = vec3(p_rel[k]), matrix_rows(R_rel[k])
    e, psi, e_R = edge_errors(p, R, is_tail, g[D2], flat_rows(g, R_DES))
    p_norm1 = abs(p[0]) + abs(p[1]) + abs(p[2])
    dq = 0.0 if is_tail else 4.0 * UNIT * p_norm1  # q = −R_i_jᵀ p for the head
    qq = e + g[D2]
    q_norm1 = p_norm1 * (1.0 if is_tail else 1.7320508075688772)  # |q|₁ ≤ √3 |p|₁ for the head
    de = 2.0 * q_norm1 * dq + 3.0 * UNIT * qq + UNIT * (qq + g[D2])
    dpsi = 14.0 * UNIT  # ½(3 − tr A) with A = Q R_des, entries of rotations (|A_ab| ≤ 1)
    de_R = 10.0 * UNIT  # A_ab − A_ba
    dxi_e, dw_e, w_e = distance_bounds(e, de, t, g[C_COL], g[C_CON], g[RHO_E_FLOOR], g[DECAY_E], saturation_margin)
    dxi_psi, dw_psi, w_psi = orientation_bounds(
        psi, dpsi, t, g[RHO_PSI_0], g[RHO_PSI_INF], g[DECAY_PSI], saturation_margin
    )
    bound_edge[k, E] = de
    bound_edge[k, PSI] = dpsi
    bound_edge[k, XI_E] = dxi_e
    bound_edge[k, XI_PSI] = dxi_psi
    bound_edge[k, MARGIN_E] = dxi_e / min(g[C_COL], g[C_CON]) + 2.0 * UNIT
    bound_edge[k, MARGIN_PSI] = dxi_psi + UNIT
    e_R_norm1 = abs(e_R[0]) + abs(e_R[1]) + abs(e_R[2])
    dv, sizes = work[DV], work[SIZES]
    for c in range(3):
        term = abs(w_e * p[c])  # w_e·(−p_c)
        dv[c] += abs(p[c]) * dw_e + UNIT * term
        sizes[c] += term
        if is_tail:
            a, da = abs(e_R[c]), de_R  # α e_R = −e_R
        else:
            a = abs(R[c][0] * e_R[0] + R[c][1] * e_R[1] + R[c][2] * e_R[2])  # α e_R = R_i_j e_R
            da = 18.0 * UNIT + 3.0 * UNIT * e_R_norm1
        dv[3 + c] += a * dw_psi + abs(w_psi) * da + UNIT * abs(w_psi) * a
        sizes[3 + c] += abs(w_psi) * a


@formula
def wrench_bounds(c, t, e_v, de_v, gains, start, rho_v0_bound, i, u_before_limit):
    """(Δξ_v, Δu before the actuator limits) of channel c of :func:`formation_agent.controller.wrench`;
    ``u_before_limit`` receives u_c as computed before :func:`formation_agent.controller.limit_wrench`."""
    tau = t - start[i, T0]
    rho_0 = start[i, START_RHO_V0 + c]
    rho_inf, decay = gains[RHO_V_INF + c], gains[DECAY_V + c]
    rho = funnels.rho(tau, rho_0, rho_inf, decay)
    drho = rho_v0_bound[i, c] * np.exp(-decay * tau) + rho_bound(tau, rho_0, rho_inf, decay, rho)
    xi = e_v / rho
    dxi = de_v / rho + abs(xi) * drho / rho + UNIT * abs(xi)
    keep = 1.0 - gains[SATURATION_MARGIN]
    x = abs(xi)
    if funnels.margin_v(xi) < gains[SATURATION_MARGIN]:
        x = keep
    worst = min(x + dxi, keep)  # the slope grows with |ξ_v|
    r, T = funnels.r_v(x), funnels.t_v(x)
    gamma = gains[GAMMA]
    u = gamma / rho * r * T
    u_before_limit[c] = u
    rel_r = 3.0 * UNIT + 2.0 * UNIT * x * x / (1.0 - x * x)
    rel_y = UNIT + UNIT * (1.0 + x) / (1.0 + x) + UNIT * (1.0 + x) / (1.0 - x)
    dT = rel_y + KAPPA * UNIT * abs(T)
    du = gamma / rho * (velocity_wrench_slope(worst) * dxi + T * r * rel_r + r * dT) + u * (drho / rho + 3.0 * UNIT)
    return dxi, du


#: rows of the scratch ``work`` (4, 6) of :func:`answer_bounds`
DV, SIZES, DE_V, U_RAW = range(4)


@kernel
def answer_bounds(
    t, i, lo, hi, p_rel, R_rel, v_measured, agents, ends, start, out, rho_v0_bound, work, bound_out, bound_edge
):
    """Bounds of agent i's step at t [s], after :func:`formation_agent.controller.agent_step` filled row
    i of ``out`` from the same inputs: row i of ``bound_out`` at U, V_DES, XI_V, MARGIN_V and rows
    lo:hi of ``bound_edge``; ``work`` (4, 6) is scratch.

    At the agent's first step (``start[i, T0] == t`` and ``rho_v0_bound[i]`` NaN) the bound of its
    velocity funnel's start is set; for a file's fixed ρ_v0 it is 0.
    """
    gains = agents[i]
    sat = gains[SATURATION_MARGIN]
    delta = gains[DELTA]
    for r in range(4):
        for c in range(6):
            work[r, c] = 0.0
    for k in range(lo, hi):
        end_bounds(p_rel, R_rel, ends[k], k, t, sat, bound_edge, work)
    m = hi - lo
    row = bound_out[i]
    for c in range(6):
        # a sum of m terms from 0, then the product with −δ
        size = work[SIZES, c]
        row[V_DES + c] = delta * (work[DV, c] + m * UNIT * size) + UNIT * delta * size
        work[DE_V, c] = row[V_DES + c] + UNIT * abs(v_measured[c] - out[i, V_DES + c])
    if start[i, T0] == t and np.isnan(rho_v0_bound[i, 0]):
        auto = np.isnan(gains[RHO_V0])
        for c in range(6):
            rho_v0 = start[i, START_RHO_V0 + c]
            rho_v0_bound[i, c] = gains[AUTO_SCALE] * work[DE_V, c] + 2.0 * UNIT * rho_v0 if auto else 0.0
    u_raw = work[U_RAW]
    for c in range(6):
        e_v = v_measured[c] - out[i, V_DES + c]
        dxi, du = wrench_bounds(c, t, e_v, work[DE_V, c], gains, start, rho_v0_bound, i, u_raw)
        row[XI_V + c] = dxi
        row[MARGIN_V + c] = dxi
        row[U + c] = du
    if out[i, REASON] == REASON_NON_FINITE:
        for c in range(6):
            row[U + c] = 0.0  # both answers are zero
        return
    for first, limit in ((0, gains[MAX_FORCE]), (3, gains[MAX_TORQUE])):
        norm = np.sqrt(u_raw[first] ** 2 + u_raw[first + 1] ** 2 + u_raw[first + 2] ** 2)
        if norm > limit * (1.0 - 1e-9):
            # scaling onto the ball is 1-Lipschitz in the 2-norm: every component moves by at most
            # the norm of the vector's error, itself at most its 1-norm
            total = row[U + first] + row[U + first + 1] + row[U + first + 2] + 5.0 * UNIT * limit
            for c in range(first, first + 3):
                row[U + c] = total


#: the columns of :class:`formation_agent.controller.ControlOutput`'s fields in the controller's
#: outputs: per agent (``out``) or per edge end (``edge_out``)
AGENT_FIELDS = {"wrench": U, "v_des": V_DES, "xi_v": XI_V, "margin_v": MARGIN_V}
END_FIELDS = {"e": E, "psi": PSI, "xi_e": XI_E, "xi_psi": XI_PSI, "margin_e": MARGIN_E, "margin_psi": MARGIN_PSI}


class BoundedController(AgentController):
    """An agent's controller that also bounds each step's round-off, for comparing its outputs with
    another computation's (a recorded wrench, another code form or host): after :meth:`compute`,
    :meth:`tolerances` says how far each output of another correct computation of that step may lie
    (:func:`tolerance` of :func:`answer_bounds`); after :meth:`fault_output`, zero (the zero wrench is
    exact everywhere)."""

    def __init__(self, view: AgentView) -> None:
        super().__init__(view)
        n = len(self.neighbours)
        self._rho_v0_bound = np.full((1, 6), np.nan)
        self._work = np.zeros((4, 6))
        self._bound_out, self._bound_edge = new_outputs(1, n)

    def reset(self) -> None:
        super().reset()
        self._rho_v0_bound[:] = np.nan

    def compute(
        self,
        t: float,
        relative_poses: Mapping[str, tuple[Sequence[float], Sequence[Sequence[float]]]],
        v_measured: Sequence[float],
    ) -> ControlOutput:
        out = super().compute(t, relative_poses, v_measured)
        v = np.asarray(v_measured, dtype=np.float64)
        answer_bounds(
            float(t), 0, 0, len(self.neighbours), self._p, self._R, v, self._agents, self._ends, self._start,
            self._out, self._rho_v0_bound, self._work, self._bound_out, self._bound_edge,
        )  # fmt: skip
        return out

    def fault_output(self, t: float, message: str) -> ControlOutput:
        self._bound_out[:] = 0.0
        self._bound_edge[:] = 0.0
        return super().fault_output(t, message)

    @property
    def wrench_tolerance(self) -> np.ndarray:
        """(6,) [N, N·m]: how far another correct computation of the last step's wrench may lie."""
        return np.asarray(tolerance(self._bound_out[0, U : U + 6]))

    def tolerances(self) -> dict[str, np.ndarray]:
        """Of the last step, per field of :class:`ControlOutput`: (6,) per agent field, one per edge end
        (the order of :attr:`neighbours`) per edge field."""
        n = len(self.neighbours)
        result = {k: np.asarray(tolerance(self._bound_out[0, c : c + 6])) for k, c in AGENT_FIELDS.items()}
        result.update({k: np.asarray(tolerance(self._bound_edge[:n, c])) for k, c in END_FIELDS.items()})
        return result
