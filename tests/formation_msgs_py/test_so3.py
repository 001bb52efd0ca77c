"""SO(3) kernels and rotation conversions: round trips, tiny angles, near-π rotations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from formation_msgs_py import rotations, so3

RNG = np.random.default_rng(20261122)


def random_rotations(n: int) -> np.ndarray:
    return Rotation.random(n, random_state=7).as_matrix()


def exp_rows(theta: np.ndarray) -> np.ndarray:
    """exp_so3 of every row of (n, 3) rotation vectors."""
    return np.array([so3.exp_so3(row) for row in theta])


def test_small_products_and_vee() -> None:
    """cross3, matvec3, matTvec3, transpose3, matmul3 on row tuples (as compiled callers pass them)
    equal numpy's to rounding (1e-14 on entries of order 1); the readers are exact; vee inverts S(w)."""
    w, x = RNG.normal(size=(2, 50, 3))
    A, B = RNG.normal(size=(2, 50, 3, 3))
    for k in range(50):
        rows_A, rows_B = so3.matrix_rows(A[k]), so3.flat_rows(B[k].ravel(), 0)
        assert rows_A == tuple(map(tuple, A[k])) and rows_B == tuple(map(tuple, B[k]))
        assert so3.vec3(x[k]) == tuple(x[k])
        np.testing.assert_allclose(so3.cross3(so3.vec3(w[k]), so3.vec3(x[k])), np.cross(w[k], x[k]), atol=1e-14)
        np.testing.assert_allclose(so3.matvec3(rows_A, so3.vec3(x[k])), A[k] @ x[k], atol=1e-14)
        np.testing.assert_allclose(so3.matTvec3(rows_A, so3.vec3(x[k])), A[k].T @ x[k], atol=1e-14)
        np.testing.assert_array_equal(so3.transpose3(rows_A), A[k].T)
        np.testing.assert_allclose(so3.matmul3(rows_A, rows_B), A[k] @ B[k], atol=1e-14)
        np.testing.assert_allclose(so3.matmul3(so3.transpose3(rows_A), rows_B), A[k].T @ B[k], atol=1e-14)
        out = np.empty((3, 3))
        so3.set3x3(out, rows_B)
        np.testing.assert_array_equal(out, B[k])
        S = np.cross(np.eye(3), -w[k]).T  # S(w): column j is w × e_j
        np.testing.assert_allclose(S @ x[k], np.cross(w[k], x[k]), atol=1e-14)
        np.testing.assert_allclose(rotations.vee(S), w[k], atol=0)


@pytest.mark.parametrize("scale", [1e-12, 1e-6, 1e-3, 1.0, np.pi - 1e-9])
def test_exp_matches_scipy(scale: float) -> None:
    """exp_so3 agrees with scipy to rounding, from tiny angles to near π."""
    axes = RNG.normal(size=(20, 3))
    theta = axes / np.linalg.norm(axes, axis=1, keepdims=True) * scale
    np.testing.assert_allclose(exp_rows(theta), Rotation.from_rotvec(theta).as_matrix(), atol=2e-15)
    assert rotations.orthonormality_error(exp_rows(theta)) < 1e-14


def test_log_exp_round_trip_near_pi() -> None:
    """log(exp(θ)) = θ for angles below π, including 1e-9 below it."""
    axes = RNG.normal(size=(20, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for angle in (1e-10, 0.3, 3.0, np.pi - 1e-9):
        theta = axes * angle
        back = np.array([rotations.log_so3(R) for R in exp_rows(theta)])
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
        np.testing.assert_allclose(np.array(rotations.matrix_from_quaternion(*q)), R, atol=2e-15)
        ref = Rotation.from_matrix(R).as_quat()
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
    np.testing.assert_allclose(R, ref, atol=1e-15)
    np.testing.assert_allclose(
        rotations.matrix_from_axis_angle([0, 0, 2.0], np.pi / 2), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15
    )
    with pytest.raises(rotations.RotationError, match="no direction"):
        rotations.matrix_from_axis_angle([0, 0, 0], 1.0)
