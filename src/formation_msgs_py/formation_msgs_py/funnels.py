"""Performance functions (funnels) and their transforms, as in the paper's Steps I and II.

Shared by the controller (which evaluates them on local measurements) and by the analysis
(which evaluates them on ground truth), so both check the same funnels.

Distance funnel of edge k (``e_k = ‖p_k2 − p_k1‖² − d_k²``, m²)::

    ρ_e(t) = (1 − ρ_e∞/C_max)·exp(−l_e t) + ρ_e∞/C_max,   C_max = max(C_col, C_con)
    −C_col·ρ_e(t) < e_k(t) < C_con·ρ_e(t)
    ξ_e = e/ρ_e ∈ (−C_col, C_con),  T_e(x) = ln((1 + x/C_col)/(1 − x/C_con))

Orientation funnel (ψ_k ∈ [0, 2], dimensionless)::

    ρ_ψ(t) = (ρ_ψ0 − ρ_ψ∞)·exp(−l_ψ t) + ρ_ψ∞,   0 ≤ ψ < ρ_ψ(t)
    ξ_ψ = ψ/ρ_ψ ∈ [0, 1),  T_ψ(x) = −ln(1 − x)

Velocity funnel per channel (m/s or rad/s)::

    ρ_v(t) = (ρ_v0 − ρ_v∞)·exp(−l_v t) + ρ_v∞,   |e_v| < ρ_v
    ξ_v = e_v/ρ_v ∈ (−1, 1),  T_v(x) = ln((1 + x)/(1 − x))

A *margin* is the fraction of the funnel left between the error and its nearest bound:
1 at zero error, 0 on the bound, negative outside.
"""

from __future__ import annotations

import math

import numpy as np


def exp_decay(rho_0, rho_inf, decay, t):
    """(ρ0 − ρ∞)·exp(−l·t) + ρ∞; scalars or numpy arrays broadcast together."""
    return (rho_0 - rho_inf) * np.exp(-decay * t) + rho_inf


def rho_e(t, c_col: float, c_con: float, rho_inf: float, decay: float):
    """Normalised distance performance function ρ_e(t) ∈ [ρ_e∞/C_max, 1]."""
    floor = rho_inf / max(c_col, c_con)
    return exp_decay(1.0, floor, decay, t)


def rho_e_scalar(t: float, c_col: float, c_con: float, rho_inf: float, decay: float) -> float:
    """``rho_e`` for a float ``t`` without numpy overhead (controller hot path)."""
    floor = rho_inf / (c_col if c_col > c_con else c_con)
    return (1.0 - floor) * math.exp(-decay * t) + floor


def rho_scalar(t: float, rho_0: float, rho_inf: float, decay: float) -> float:
    """``exp_decay`` for floats without numpy overhead (controller hot path)."""
    return (rho_0 - rho_inf) * math.exp(-decay * t) + rho_inf


def margin_e(xi_e, c_col: float, c_con: float):
    """Distance margin: min(1 + ξ/C_col, 1 − ξ/C_con)."""
    return np.minimum(1.0 + np.asarray(xi_e) / c_col, 1.0 - np.asarray(xi_e) / c_con)


def margin_psi(xi_psi):
    """Orientation margin 1 − ξ_ψ."""
    return 1.0 - np.asarray(xi_psi)


def margin_v(xi_v):
    """Velocity margin 1 − |ξ_v| per channel."""
    return 1.0 - np.abs(np.asarray(xi_v))


def t_e(x: float, c_col: float, c_con: float) -> float:
    """T_e(x) = ln((1 + x/C_col)/(1 − x/C_con)), x ∈ (−C_col, C_con)."""
    return math.log((1.0 + x / c_col) / (1.0 - x / c_con))


def r_e(x: float, c_col: float, c_con: float) -> float:
    """r_e = dT_e/dx = 1/(C_col + x) + 1/(C_con − x)."""
    return 1.0 / (c_col + x) + 1.0 / (c_con - x)


def t_psi(x: float) -> float:
    """T_ψ(x) = −ln(1 − x), x ∈ [0, 1)."""
    return -math.log(1.0 - x)


def r_psi(x: float) -> float:
    """r_ψ = dT_ψ/dx = 1/(1 − x)."""
    return 1.0 / (1.0 - x)


def t_v(x):
    """T_v(x) = ln((1 + x)/(1 − x)), elementwise on x ∈ (−1, 1)."""
    return np.log((1.0 + x) / (1.0 - x))


def r_v(x):
    """r_v = dT_v/dx = 2/(1 − x²), elementwise."""
    return 2.0 / (1.0 - x * x)
