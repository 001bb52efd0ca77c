"""Rotations as data: checks, projection and the conversions of formation files and messages.

Conventions: ``vee`` gives the 3-vector of a skew matrix (S(w) x = w × x); rotation vectors are
axis * angle in radians; quaternions are (x, y, z, w), scalar last, the order of geometry_msgs and
of scipy's default; :func:`quaternion_of_rows` and :func:`rows_of_quaternion` are the only
quaternion conversions of the project (formulas: plain Python per message in the nodes, compiled
into the run core's measurement kernel). numpy only (scipy's
``Rotation`` for rpy, axis-angle and the logarithm, imported when used): loading a formation file
or decoding a message never imports the compiled kernels of :mod:`formation_core.so3`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from formation_core.errors import RotationError
from formation_core.numba_kernels import formula

FloatArray = NDArray[np.float64]

#: Tolerance of ``is_rotation`` on ||RᵀR − I||_F and |det R − 1|.
ROTATION_TOLERANCE = 1e-6


def vee(S: ArrayLike) -> FloatArray:
    """S⁻¹: the 3-vector of a skew matrix (or a stack)."""
    S = np.asarray(S, dtype=np.float64)
    return np.stack([S[..., 2, 1], S[..., 0, 2], S[..., 1, 0]], axis=-1)


def log_so3(R: ArrayLike) -> FloatArray:
    """Rotation vector of R (angle in [0, π]); robust near 0 and π (uses scipy)."""
    from scipy.spatial.transform import Rotation  # scipy takes ~0.4 s to import: only when used

    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_rotvec()


def is_rotation(R: ArrayLike, tol: float = ROTATION_TOLERANCE) -> bool:
    """True if R is 3×3, orthogonal and right-handed to ``tol``."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        return False
    return bool(np.linalg.norm(R.T @ R - np.eye(3)) <= tol and abs(np.linalg.det(R) - 1.0) <= tol)


def project_to_so3(M: ArrayLike) -> FloatArray:
    """Nearest rotation (Frobenius norm) to a 3×3 matrix, by SVD."""
    M = np.asarray(M, dtype=np.float64)
    if M.shape != (3, 3):
        raise RotationError(f"expected a 3x3 matrix, got shape {M.shape}")
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def orthonormality_error(R: ArrayLike) -> float:
    """max over a stack of ||RᵀR − I||_F (0 for exact rotations)."""
    R = np.asarray(R, dtype=np.float64)
    eye = np.eye(3)
    err = np.linalg.norm(np.swapaxes(R, -1, -2) @ R - eye, axis=(-2, -1))
    return float(np.max(err))


@formula
def quaternion_of_rows(rows):
    """(x, y, z, w), w ≥ 0, of a rotation given as three row tuples (Shepperd's method).

    The one conversion of a rotation to the quaternion a message carries: plain Python where a node
    encodes a message, compiled into the measurement kernel of the run core, the same operations in
    the same order (IEEE arithmetic and a correctly rounded square root: the same bits either way).
    """
    r00, r01, r02 = rows[0][0], rows[0][1], rows[0][2]
    r10, r11, r12 = rows[1][0], rows[1][1], rows[1][2]
    r20, r21, r22 = rows[2][0], rows[2][1], rows[2][2]
    tr = r00 + r11 + r22
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        w, x, y, z = (r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        w, x, y, z = (r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        w, x, y, z = (r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    return x, y, z, w


@formula
def rows_of_quaternion(x, y, z, w):
    """The rotation of a non-zero quaternion (x, y, z, w), normalised first, as three row tuples.

    The one conversion of a received quaternion to the matrix the controller reads: plain Python in
    an agent's decoder, compiled into the measurement kernel of the run core (see
    :func:`quaternion_of_rows`).
    """
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return (
        (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)),
        (2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)),
        (2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)),
    )


def quaternion_from_matrix(R: np.ndarray | Sequence[Sequence[float]]) -> tuple[float, float, float, float]:
    """(x, y, z, w), w ≥ 0, of a rotation matrix (an array or nested rows): :func:`quaternion_of_rows`."""
    rows: Sequence[Sequence[float]] = R.tolist() if isinstance(R, np.ndarray) else R
    return quaternion_of_rows(rows)


def matrix_from_quaternion(x: float, y: float, z: float, w: float) -> list[list[float]]:
    """Rotation matrix (nested lists) of a quaternion; normalises it (:func:`rows_of_quaternion`).

    Raises RotationError for a zero or non-finite quaternion (no rotation to give). Messages are
    checked before they get here (formation_msgs_py.measurement_checks: the norm must be 1 to 1e-6).
    """
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not (n > 1e-12 and math.isfinite(n)):
        raise RotationError(f"quaternion ({x!r}, {y!r}, {z!r}, {w!r}) has no rotation (norm {n!r})")
    return [list(row) for row in rows_of_quaternion(x, y, z, w)]


def matrix_from_rpy(rpy: ArrayLike) -> FloatArray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (REP 103 fixed-axis roll, pitch, yaw), radians."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", np.asarray(rpy, dtype=np.float64)).as_matrix()


def matrix_from_axis_angle(axis: ArrayLike, angle: float) -> FloatArray:
    """Rotation of ``angle`` radians about ``axis`` (normalised; must be non-zero)."""
    axis = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(axis)
    if not np.isfinite(n) or n < 1e-12:
        raise RotationError(f"axis {axis.tolist()} has no direction")
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(axis / n * float(angle)).as_matrix()
