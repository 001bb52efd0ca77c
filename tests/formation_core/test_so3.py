"""SO(3) kernels and rotation conversions: round trips, tiny angles, near-π rotations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from formation_core import rotations, so3

pytestmark = pytest.mark.numeric

RNG = np.random.default_rng(20261122)
#: unit round-off of IEEE double
UNIT = 2.0**-53


def order_bound(abs_products: np.ndarray) -> np.ndarray:
    """How far two computations of sums of up to 3 products may be apart, whatever their order (numpy may
    sum through BLAS or SIMD): each within γ₃·Σ|products| of the exact sum, γ₃ = 3u/(1 − 3u)."""
    return 2.0 * 3.0 * UNIT / (1.0 - 3.0 * UNIT) * abs_products


def random_rotations(n: int) -> np.ndarray:
    return Rotation.random(n, random_state=7).as_matrix()


def exp_rows(theta: np.ndarray) -> np.ndarray:
    """exp_so3 of every row of (n, 3) rotation vectors."""
    return np.array([so3.exp_so3(row) for row in theta])


def test_small_products_and_vee() -> None:
    """cross3, matvec3, matTvec3, transpose3, matmul3 on row tuples (as compiled callers pass them)
    equal numpy's within the rounding of a sum's order (:func:`order_bound`); the readers are exact;
    vee inverts S(w)."""
    w, x = RNG.normal(size=(2, 50, 3))
    A, B = RNG.normal(size=(2, 50, 3, 3))

    def near(ours, theirs, bound) -> None:
        assert np.all(np.abs(np.asarray(ours) - theirs) <= order_bound(bound))

    for k in range(50):
        rows_A, rows_B = so3.matrix_rows(A[k]), so3.flat_rows(B[k].ravel(), 0)
        assert rows_A == tuple(map(tuple, A[k])) and rows_B == tuple(map(tuple, B[k]))
        assert so3.vec3(x[k]) == tuple(x[k])
        aw, ax, aA, aB = np.abs(w[k]), np.abs(x[k]), np.abs(A[k]), np.abs(B[k])
        cross_terms = np.array(
            [aw[1] * ax[2] + aw[2] * ax[1], aw[2] * ax[0] + aw[0] * ax[2], aw[0] * ax[1] + aw[1] * ax[0]]
        )
        near(so3.cross3(so3.vec3(w[k]), so3.vec3(x[k])), np.cross(w[k], x[k]), cross_terms)
        near(so3.matvec3(rows_A, so3.vec3(x[k])), A[k] @ x[k], aA @ ax)
        near(so3.matTvec3(rows_A, so3.vec3(x[k])), A[k].T @ x[k], aA.T @ ax)
        np.testing.assert_array_equal(so3.transpose3(rows_A), A[k].T)
        near(so3.matmul3(rows_A, rows_B), A[k] @ B[k], aA @ aB)
        near(so3.matmul3(so3.transpose3(rows_A), rows_B), A[k].T @ B[k], aA.T @ aB)
        out = np.empty((3, 3))
        so3.set3x3(out, rows_B)
        np.testing.assert_array_equal(out, B[k])
        S = np.cross(np.eye(3), -w[k]).T  # S(w): column j is w × e_j
        near(S @ x[k], np.cross(w[k], x[k]), cross_terms)
        np.testing.assert_allclose(rotations.vee(S), w[k], atol=0)


@pytest.mark.parametrize("scale", [1e-12, 1e-6, 1e-3, 1.0, np.pi - 1e-9])
def test_exp_matches_scipy(scale: float) -> None:
    """exp_so3 agrees with scipy to rounding, from tiny angles to near π."""
    axes = RNG.normal(size=(20, 3))
    theta = axes / np.linalg.norm(axes, axis=1, keepdims=True) * scale
    # entries ≤ 1, each side from sin, cos (libm: < 1 ulp) and about ten roundings: a few ulp(1) = 2.2e-16
    np.testing.assert_allclose(exp_rows(theta), Rotation.from_rotvec(theta).as_matrix(), atol=2e-15)
    # RᵀR − I: sums of 3 products of entries ≤ 1, each entry a few ulps off: well under 50 ulp(1)
    assert rotations.orthonormality_error(exp_rows(theta)) < 1e-14


def test_log_exp_round_trip_near_pi() -> None:
    """log(exp(θ)) = θ for angles below π, including 1e-9 below it."""
    axes = RNG.normal(size=(20, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for angle in (1e-10, 0.3, 3.0, np.pi - 1e-9):
        theta = axes * angle
        back = np.array([rotations.log_so3(R) for R in exp_rows(theta)])
        # log's condition number grows like 1/sin θ near π (1e9 at π − 1e-9): a few ulps of R become 1e-7;
        # elsewhere it is of order 1, and 1e-12 leaves room for the acos near θ = 0's cancellation
        np.testing.assert_allclose(back, theta, atol=1e-7 if angle > 3.1 else 1e-12)


def test_dexpinv_is_the_rate_of_the_exponential_coordinates() -> None:
    """exp(Θ + h·dexpinv(Θ, ω)) = exp(Θ)·exp(hω) + O(h²): the RKMK chart is right-trivialised."""
    theta, omega = RNG.normal(size=(2, 30, 3))
    for h in (1e-4, 1e-5):
        rates = np.array([so3.dexpinv_so3(a, b) for a, b in zip(theta, omega)])
        lhs = exp_rows(theta + h * rates)
        rhs = exp_rows(theta) @ exp_rows(h * omega)
        # second-order remainder: error / h² stays bounded (tolerance 10 h²)
        assert np.abs(lhs - rhs).max() < 10 * h * h
    tiny = theta * 1e-9
    rates = np.array([so3.dexpinv_so3(a, b) for a, b in zip(tiny, omega)])
    # the series' next term is |θ|²|ω|/12 ≈ 1e-18; both sides round ω (|ω| < 4: ulp 4.4e-16) once or twice
    np.testing.assert_allclose(rates, omega + 0.5 * np.cross(tiny, omega), atol=1e-15)


def test_quaternion_round_trip_all_branches() -> None:
    """Matrix → quaternion → matrix is exact to 1e-15, near π and identity too (all four branches)."""
    mats = list(random_rotations(200))
    for axis in np.eye(3):
        mats.append(Rotation.from_rotvec(axis * (np.pi - 1e-12)).as_matrix())
    mats.append(np.eye(3))
    for R in mats:
        q = rotations.quaternion_from_matrix(R)
        assert q[3] >= 0
        # entries ≤ 1 through a square root and about ten roundings each way: a few ulp(1) = 2.2e-16
        np.testing.assert_allclose(np.array(rotations.matrix_from_quaternion(*q)), R, atol=2e-15)
        ref = Rotation.from_matrix(R).as_quat()
        # scipy picks its branch by another rule: near a branch's edge the two differ by more roundings,
        # amplified by 1/(4q_max) ≤ 1/2; 1e-12 is far below any wrong sign or order (order 1)
        assert min(np.abs(ref - q).max(), np.abs(ref + q).max()) < 1e-12


def test_projection_of_the_papers_R2() -> None:
    """R_2(0) as printed is not a rotation (‖RᵀR − I‖_F ≈ 0.37); its projection is."""
    R2 = np.array([[-0.8253, 0, 0.5646], [0, 1, 0.2562], [-0.5646, 0, -0.8253]])
    assert not rotations.is_rotation(R2)
    assert np.linalg.norm(R2.T @ R2 - np.eye(3)) == pytest.approx(0.37, abs=0.01)
    P = rotations.project_to_so3(R2)
    assert rotations.is_rotation(P, tol=1e-14)
    assert np.linalg.norm(P - R2) < 0.2


def test_rpy_and_axis_angle() -> None:
    """rpy is fixed-axis x-y-z (R = Rz Ry Rx); axis-angle normalises the axis."""
    R = rotations.matrix_from_rpy([0.1, -0.2, 0.3])
    ref = Rotation.from_euler("z", 0.3).as_matrix() @ Rotation.from_euler("y", -0.2).as_matrix()
    ref = ref @ Rotation.from_euler("x", 0.1).as_matrix()
    # entries ≤ 1 from three sines and cosines (< 1 ulp each) and two 3×3 products on each side: in the
    # worst case 2·(2·3 + 3) ulp(1) ≈ 4e-15 apart
    np.testing.assert_allclose(R, ref, atol=4e-15)
    # cos(π/2) rounds to 6.1e-17, sin(π/2) to 1: the other entries are products with exact zeros and ones
    np.testing.assert_allclose(
        rotations.matrix_from_axis_angle([0, 0, 2.0], np.pi / 2), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15
    )
    with pytest.raises(rotations.RotationError, match="no direction"):
        rotations.matrix_from_axis_angle([0, 0, 0], 1.0)
