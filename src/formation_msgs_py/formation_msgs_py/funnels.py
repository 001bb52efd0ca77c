"""Performance functions (funnels), their transforms T and derivatives r, and the margins.

The one home of these formulas: the controller evaluates them on local measurements, the run
core and the reports on ground truth, the rate analysis on ρ_v. Each is a
:func:`formation_msgs_py.compiled.formula`: compiled into the kernels that call it on floats,
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

from formation_msgs_py.compiled import formula


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
