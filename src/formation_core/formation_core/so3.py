"""SO(3) formulas of the controller, the plant and the measurement model.

The 3-vector / 3×3 products, ``exp_rows`` (Rodrigues) and ``dexpinv`` (the RKMK chart) are
formulas compiled into the kernels that call them (:func:`formation_core.numba_kernels.formula`).
Compiled callers pass 3-vectors as tuples and 3×3 matrices as three row tuples, read from arrays
by :func:`vec3`, :func:`matrix_rows` and :func:`flat_rows`: one argument type per formula, so each
is compiled once. From Python they are plain numpy (arrays work too) and importing this module
does not import numba. Rotation vectors are axis * angle in radians. Rotations as data (checks,
projection, quaternion / rpy / axis-angle conversions) live in :mod:`formation_core.rotations`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from formation_core.numba_kernels import formula

FloatArray = NDArray[np.float64]


# --- reading arrays into tuples -------------------------------------------------------------------


@formula
def vec3(a):
    """The 3-vector ``a`` (an array row) as a tuple."""
    return (a[0], a[1], a[2])


@formula
def matrix_rows(A):
    """The 3×3 array ``A`` as three row tuples."""
    return ((A[0, 0], A[0, 1], A[0, 2]), (A[1, 0], A[1, 1], A[1, 2]), (A[2, 0], A[2, 1], A[2, 2]))


@formula
def flat_rows(row, at):
    """The 3×3 matrix stored row-major in ``row[at:at + 9]``, as three row tuples."""
    return (
        (row[at], row[at + 1], row[at + 2]),
        (row[at + 3], row[at + 4], row[at + 5]),
        (row[at + 6], row[at + 7], row[at + 8]),
    )


@formula
def set3x3(out, rows):
    """out[:, :] = rows (a 3×3 array from three row tuples), element by element."""
    for i in range(3):
        for j in range(3):
            out[i, j] = rows[i][j]


# --- 3-vectors (x, y, z) and 3×3 matrices (three rows) ---------------------------------------------


@formula
def add3(a, b):
    """a + b."""
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@formula
def sub3(a, b):
    """a − b."""
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@formula
def scale3(s, a):
    """s·a."""
    return (s * a[0], s * a[1], s * a[2])


@formula
def cross3(a, b):
    """a × b."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@formula
def matvec3(A, x):
    """A x."""
    return (
        A[0][0] * x[0] + A[0][1] * x[1] + A[0][2] * x[2],
        A[1][0] * x[0] + A[1][1] * x[1] + A[1][2] * x[2],
        A[2][0] * x[0] + A[2][1] * x[1] + A[2][2] * x[2],
    )


@formula
def matTvec3(A, x):
    """Aᵀ x."""
    return (
        A[0][0] * x[0] + A[1][0] * x[1] + A[2][0] * x[2],
        A[0][1] * x[0] + A[1][1] * x[1] + A[2][1] * x[2],
        A[0][2] * x[0] + A[1][2] * x[1] + A[2][2] * x[2],
    )


@formula
def transpose3(A):
    """Aᵀ."""
    return ((A[0][0], A[1][0], A[2][0]), (A[0][1], A[1][1], A[2][1]), (A[0][2], A[1][2], A[2][2]))


@formula
def matmul3(A, B):
    """A B: row i is Bᵀ (row i of A)."""
    return (matTvec3(B, A[0]), matTvec3(B, A[1]), matTvec3(B, A[2]))


@formula
def exp_rows(theta):
    """exp(S(θ)) of a rotation vector θ [rad] as three row tuples, by Rodrigues' formula.

    R = cos θ·I + (sin θ/θ)·S(θ) + ((1 − cos θ)/θ²)·θθᵀ, by its series near 0.
    """
    tx, ty, tz = theta[0], theta[1], theta[2]
    a2 = tx * tx + ty * ty + tz * tz
    if a2 < 1e-8:  # the closed forms lose digits near 0
        A = 1.0 - a2 / 6.0 + a2 * a2 / 120.0
        B = 0.5 - a2 / 24.0 + a2 * a2 / 720.0
        C = 1.0 - a2 / 2.0 + a2 * a2 / 24.0
    else:
        a = np.sqrt(a2)
        A = np.sin(a) / a
        C = np.cos(a)
        B = (1.0 - C) / a2
    return (
        (C + B * tx * tx, B * tx * ty - A * tz, B * tx * tz + A * ty),
        (B * ty * tx + A * tz, C + B * ty * ty, B * ty * tz - A * tx),
        (B * tz * tx - A * ty, B * tz * ty + A * tx, C + B * tz * tz),
    )


def exp_so3(theta: ArrayLike) -> FloatArray:
    """exp(S(θ)) (3,3) of a rotation vector θ (3,) [rad]."""
    return np.array(exp_rows(np.asarray(theta, dtype=np.float64)))


@formula
def dexpinv(theta, omega):
    """Θ̇ such that R0·exp(S(Θ)) moves with body rate ω: Θ̇ = dexp⁻¹_{−Θ}(ω) (RKMK chart).

    dexp⁻¹_{−Θ}(ω) = ω + ½ Θ×ω + c·Θ×(Θ×ω), c = (1 − (θ/2)cot(θ/2))/θ² (series near 0).
    """
    a2 = theta[0] * theta[0] + theta[1] * theta[1] + theta[2] * theta[2]
    if a2 < 1e-6:
        c = 1.0 / 12.0 + a2 / 720.0
    else:
        half = 0.5 * np.sqrt(a2)
        c = (1.0 - half / np.tan(half)) / a2
    txw = cross3(theta, omega)
    return add3(add3(omega, scale3(0.5, txw)), scale3(c, cross3(theta, txw)))


def dexpinv_so3(theta: ArrayLike, omega: ArrayLike) -> FloatArray:
    """:func:`dexpinv` as a (3,) array."""
    return np.array(dexpinv(np.asarray(theta, dtype=np.float64), np.asarray(omega, dtype=np.float64)))
