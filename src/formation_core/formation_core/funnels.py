"""Performance functions (funnels), their transforms T and derivatives r, and the margins.

The one home of these formulas: the controller evaluates them on local measurements, the run
core and the reports on ground truth, the rate analysis on ρ_v. Each is a
:func:`formation_core.numba_kernels.formula`: compiled into the kernels that call it on floats,
plain numpy (elementwise on arrays) when called from Python.

Distance funnel of edge k (``e_k = ‖p_k2 − p_k1‖² − d_k²``, m²; paper eq. ppc ineq, Step I)::

    ρ_e(t) = (1 − ρ_e∞/C_max)·exp(−l_e t) + ρ_e∞/C_max,   C_max = max(C_col, C_con)
    −C_col·ρ_e(t) < e_k(t) < C_con·ρ_e(t)
    ξ_e = e/ρ_e ∈ (−C_col, C_con),  T_e(x) = ln((1 + x/C_col)/(1 − x/C_con))

Orientation funnel (ψ_k ∈ [0, 2], dimensionless)::

    ρ_ψ(t) = (ρ_ψ0 − ρ_ψ∞)·exp(−l_ψ t) + ρ_ψ∞,   0 ≤ ψ < ρ_ψ(t)
    ξ_ψ = ψ/ρ_ψ ∈ [0, 1),  T_ψ(x) = −ln(1 − x)

Velocity funnel per channel (m/s or rad/s; Step II)::

    ρ_v(t) = (ρ_v0 − ρ_v∞)·exp(−l_v t) + ρ_v∞,   |e_v| < ρ_v
    ξ_v = e_v/ρ_v ∈ (−1, 1),  T_v(x) = ln((1 + x)/(1 − x))

A *margin* is the fraction of the funnel left between the error and its nearest bound:
1 at zero error, 0 on the bound, negative outside.
"""

from __future__ import annotations

import numpy as np

from formation_core.numba_kernels import formula
from formation_core.so3 import matmul3, matrix_rows, vec3


@formula
def rho(t, rho_0, rho_inf, decay):
    """(ρ0 − ρ∞)·exp(−l·t) + ρ∞: ρ_ψ, ρ_v, and ρ_e with ρ0 = 1 and ρ∞ = :func:`rho_e_floor`."""
    return (rho_0 - rho_inf) * np.exp(-decay * t) + rho_inf


@formula
def rho_e_floor(c_col, c_con, rho_e_inf):
    """ρ_e(∞) of the normalised distance funnel: ρ_e∞ / max(C_col, C_con)."""
    return rho_e_inf / np.maximum(c_col, c_con)


@formula
def t_e(x, c_col, c_con):
    """T_e(x) = ln((1 + x/C_col)/(1 − x/C_con)), x ∈ (−C_col, C_con) (Step I-b)."""
    return np.log((1.0 + x / c_col) / (1.0 - x / c_con))


@formula
def r_e(x, c_col, c_con):
    """r_e = dT_e/dx = 1/(C_col + x) + 1/(C_con − x)."""
    return 1.0 / (c_col + x) + 1.0 / (c_con - x)


@formula
def r_psi(x):
    """r_ψ = dT_ψ/dx = 1/(1 − x), x ∈ [0, 1) (T_ψ itself does not enter the law)."""
    return 1.0 / (1.0 - x)


@formula
def t_v(x):
    """T_v(x) = ln((1 + x)/(1 − x)), x ∈ (−1, 1) (Step II-b)."""
    return np.log((1.0 + x) / (1.0 - x))


@formula
def r_v(x):
    """r_v = dT_v/dx = 2/(1 − x²)."""
    return 2.0 / (1.0 - x * x)


@formula
def margin_e(xi_e, c_col, c_con):
    """Distance margin min(1 + ξ_e/C_col, 1 − ξ_e/C_con)."""
    return np.minimum(1.0 + xi_e / c_col, 1.0 - xi_e / c_con)


@formula
def margin_psi(xi_psi):
    """Orientation margin 1 − ξ_ψ."""
    return 1.0 - xi_psi


@formula
def margin_v(xi_v):
    """Velocity margin 1 − |ξ_v| per channel."""
    return 1.0 - np.abs(xi_v)


@formula
def edge_errors(p_tail, p_head, R_tail, R_head, d2, R_des):
    """(e_k [m²], ψ_k) of edge k from world poses, the errors its funnels bound: e = ‖p_head − p_tail‖² − d_k,des² and
    ψ = ½ tr(I − R_desᵀ R_headᵀ R_tail) = ½(3 − Σ (R_head R_des)∘R_tail), d2 = d_k,des² [m²].

    Vectors are 3-tuples and matrices row tuples (:func:`formation_core.so3.vec3`,
    :func:`formation_core.so3.matrix_rows`) of floats, or of numpy arrays (elementwise).
    """
    d = (p_head[0] - p_tail[0], p_head[1] - p_tail[1], p_head[2] - p_tail[2])
    e = d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - d2
    A = matmul3(R_head, R_des)
    trace = 0.0
    for a in range(3):
        for b in range(3):
            trace += A[a][b] * R_tail[a][b]
    return e, 0.5 * (3.0 - trace)


def edge_errors_from_arrays(
    p_tail: np.ndarray, p_head: np.ndarray, R_tail: np.ndarray, R_head: np.ndarray, d_des: float, R_des: np.ndarray
) -> tuple[float, float]:
    """(e [m²], ψ) of one edge from arrays: positions (3,) and R_world_body (3,3) of its tail and head,
    its desired distance [m] and relative rotation (:func:`edge_errors`)."""
    e, psi = edge_errors(
        vec3(p_tail), vec3(p_head), matrix_rows(R_tail), matrix_rows(R_head), d_des**2, matrix_rows(R_des)
    )
    return float(e), float(psi)
