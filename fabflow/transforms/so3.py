"""Rotations (SO(3)) as plain numpy arrays, batch-capable.

Every function accepts leading batch dimensions: a rotation vector is ``(..., 3)``,
a rotation matrix ``(..., 3, 3)``, a quaternion ``(..., 4)`` in the order
``(w, x, y, z)``. Angles are radians. Matrices act on column vectors
(``p_a = R_a_b @ p_b``).

Validation policy (used by :class:`fabflow.transforms.Pose` and the vendor
converters):

* A rotation matrix is accepted when ``max |R^T R - I| <= ROTATION_TOL`` (1e-6)
  and ``det R > 0``; otherwise :class:`~fabflow.transforms.errors.RotationError`.
  Accepted matrices are used as given (not re-orthonormalized), so exact inputs
  round-trip exactly.
* A quaternion whose norm differs from 1 by at most ``QUATERNION_TOL`` (1e-6) is
  normalized; anything farther from unit norm (or zero / non-finite) raises
  :class:`~fabflow.transforms.errors.QuaternionError`. It is never used
  un-normalized.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.transforms.errors import QuaternionError, RotationError

ROTATION_TOL = 1e-6
"""Largest accepted entry of ``|R^T R - I|`` for a rotation matrix."""

QUATERNION_TOL = 1e-6
"""Largest accepted ``| |q| - 1 |`` before a quaternion is rejected instead of normalized."""

_SMALL_ANGLE = 1e-4
_GIMBAL_EPS = 1e-12

FloatArray = NDArray[np.float64]


R_FLIP_X = np.diag([1.0, -1.0, -1.0])
"""Half a turn about x: keeps x and points z down (a tool pointing down from a z-up frame)."""


def _vec3(v: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(v, dtype=float)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {a.shape}")
    return a


def _mat3(m: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(m, dtype=float)
    if a.ndim < 2 or a.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got {a.shape}")
    return a


def skew(v: ArrayLike) -> FloatArray:
    """Cross-product matrix: ``skew(v) @ w == np.cross(v, w)``.

    Parameters
    ----------
    v
        Vectors, shape ``(..., 3)``.

    Returns
    -------
    numpy.ndarray
        Skew-symmetric matrices, shape ``(..., 3, 3)``.
    """
    v = _vec3(v, "v")
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    # filled in place: a third of the time of stacking rows (exp_so3 runs at every step)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -z, y
    out[..., 1, 0], out[..., 1, 2] = z, -x
    out[..., 2, 0], out[..., 2, 1] = -y, x
    return out


def exp_so3(rotvec: ArrayLike) -> FloatArray:
    """Rotation matrix of a rotation vector (Rodrigues' formula).

    Parameters
    ----------
    rotvec
        Rotation vectors ``angle * axis`` (radians), shape ``(..., 3)``. Exact near
        zero (series expansion below 1e-4 rad).

    Returns
    -------
    numpy.ndarray
        Rotation matrices, shape ``(..., 3, 3)``.
    """
    v = _vec3(rotvec, "rotvec")
    th2 = np.einsum("...i,...i->...", v, v)
    th = np.sqrt(th2)
    small = th < _SMALL_ANGLE
    th_safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(th_safe) / th_safe)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(th_safe)) / th_safe**2)
    c = np.where(small, 1.0 - th2 / 2.0 + th2 * th2 / 24.0, np.cos(th_safe))
    # R = cos(t) I + sin(t)/t [v]x + (1 - cos(t))/t^2 v v^T
    R = b[..., None, None] * (v[..., :, None] * v[..., None, :])
    R = R + a[..., None, None] * skew(v)
    R[..., 0, 0] += c
    R[..., 1, 1] += c
    R[..., 2, 2] += c
    return R


def quat_from_matrix(R: ArrayLike) -> FloatArray:
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix, with ``w >= 0``.

    Uses Shepperd's method (largest of the four diagonal candidates), so it is
    accurate for every rotation including 180 degrees. The matrix is not
    validated here; see :func:`check_rotation`.

    Parameters
    ----------
    R
        Rotation matrices, shape ``(..., 3, 3)``.

    Returns
    -------
    numpy.ndarray
        Quaternions, shape ``(..., 4)``, unit norm, ``w >= 0``.
    """
    R = _mat3(R, "R")
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = r00 + r11 + r22
    # Candidate k is 4 * q_k * q (in w, x, y, z order); pick the one with largest q_k^2.
    cands = np.stack(
        [
            np.stack([1.0 + tr, r21 - r12, r02 - r20, r10 - r01], -1),
            np.stack([r21 - r12, 1.0 + r00 - r11 - r22, r01 + r10, r02 + r20], -1),
            np.stack([r02 - r20, r01 + r10, 1.0 - r00 + r11 - r22, r12 + r21], -1),
            np.stack([r10 - r01, r02 + r20, r12 + r21, 1.0 - r00 - r11 + r22], -1),
        ],
        -2,
    )
    diag = np.stack(
        [1.0 + tr, 1.0 + r00 - r11 - r22, 1.0 - r00 + r11 - r22, 1.0 - r00 - r11 + r22], -1
    )
    k = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def normalize_quat(q: ArrayLike, tol: float = QUATERNION_TOL) -> FloatArray:
    """Validate and normalize quaternions ``(w, x, y, z)``.

    Parameters
    ----------
    q
        Quaternions, shape ``(..., 4)``.
    tol
        Largest accepted ``| |q| - 1 |``; farther quaternions are rejected.

    Returns
    -------
    numpy.ndarray
        Unit quaternions (sign unchanged), shape ``(..., 4)``.

    Raises
    ------
    QuaternionError
        If a quaternion is not finite or its norm is off by more than ``tol``.
    """
    q = np.asarray(q, dtype=float)
    if q.ndim == 0 or q.shape[-1] != 4:
        raise ValueError(f"quaternion must have shape (..., 4), got {q.shape}")
    n = np.linalg.norm(q, axis=-1)
    bad = ~np.isfinite(n) | (np.abs(n - 1.0) > tol)
    if np.any(bad):
        idx = np.argwhere(np.atleast_1d(bad))[0]
        where = "" if q.ndim == 1 else f" at index {tuple(int(i) for i in idx)}"
        raise QuaternionError(
            f"quaternion (w, x, y, z){where} has norm {float(np.atleast_1d(n)[tuple(idx)]):.9g};"
            f" expected a unit quaternion (|norm - 1| <= {tol:g})"
        )
    return q / n[..., None]


def matrix_from_quat(q: ArrayLike, tol: float = QUATERNION_TOL) -> FloatArray:
    """Rotation matrix of a quaternion ``(w, x, y, z)``.

    Parameters
    ----------
    q
        Quaternions, shape ``(..., 4)``; normalized if within ``tol`` of unit norm.
    tol
        See :func:`normalize_quat`.

    Returns
    -------
    numpy.ndarray
        Rotation matrices, shape ``(..., 3, 3)``.

    Raises
    ------
    QuaternionError
        If a quaternion is too far from unit norm.
    """
    q = normalize_quat(q, tol)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return np.stack(
        [
            np.stack([1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)], -1),
            np.stack([2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)], -1),
            np.stack([2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)], -1),
        ],
        -2,
    )


def rotvec_from_quat(q: ArrayLike) -> FloatArray:
    """Rotation vector of unit quaternions ``(w, x, y, z)``, angle in ``[0, pi]``.

    At exactly 180 degrees the axis sign is that of the quaternion's vector part
    (both signs describe the same rotation).

    Parameters
    ----------
    q
        Unit quaternions, shape ``(..., 4)`` (not re-validated).

    Returns
    -------
    numpy.ndarray
        Rotation vectors (radians), shape ``(..., 3)``.
    """
    q = np.asarray(q, dtype=float)
    q = np.where(q[..., :1] < 0.0, -q, q)
    w = q[..., 0]
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    small = angle < _SMALL_ANGLE
    s_safe = np.where(small, 1.0, s)
    a2 = angle * angle
    # angle / sin(angle / 2), with its series near zero
    scale = np.where(small, 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0, angle / s_safe)
    return scale[..., None] * v


def quat_from_rotvec(rotvec: ArrayLike) -> FloatArray:
    """Unit quaternion ``(w, x, y, z)`` of rotation vectors; ``w >= 0`` for angles <= pi.

    Parameters
    ----------
    rotvec
        Rotation vectors (radians), shape ``(..., 3)``.

    Returns
    -------
    numpy.ndarray
        Quaternions, shape ``(..., 4)``.
    """
    v = _vec3(rotvec, "rotvec")
    th = np.linalg.norm(v, axis=-1)
    small = th < _SMALL_ANGLE
    th_safe = np.where(small, 1.0, th)
    t2 = th * th
    # sin(th/2)/th with its series near zero
    k = np.where(small, 0.5 - t2 / 48.0 + t2 * t2 / 3840.0, np.sin(th_safe / 2.0) / th_safe)
    q = np.concatenate([np.cos(th / 2.0)[..., None], k[..., None] * v], -1)
    return q


def log_so3(R: ArrayLike) -> FloatArray:
    """Rotation vector of a rotation matrix, angle in ``[0, pi]``.

    Accurate near the identity and at 180 degrees (via Shepperd's quaternion).

    Parameters
    ----------
    R
        Rotation matrices, shape ``(..., 3, 3)``.

    Returns
    -------
    numpy.ndarray
        Rotation vectors (radians), shape ``(..., 3)``.
    """
    return rotvec_from_quat(quat_from_matrix(R))


def matrix_from_abc(a: ArrayLike, b: ArrayLike, c: ArrayLike) -> FloatArray:
    """Rotation matrix ``Rz(a) @ Ry(b) @ Rx(c)`` (KUKA A, B, C; radians).

    Parameters
    ----------
    a, b, c
        Angles in radians, broadcastable to a common shape ``(...)``.

    Returns
    -------
    numpy.ndarray
        Rotation matrices, shape ``(..., 3, 3)``.
    """
    a, b, c = np.broadcast_arrays(
        np.asarray(a, dtype=float), np.asarray(b, dtype=float), np.asarray(c, dtype=float)
    )
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    return np.stack(
        [
            np.stack([ca * cb, ca * sb * sc - sa * cc, ca * sb * cc + sa * sc], -1),
            np.stack([sa * cb, sa * sb * sc + ca * cc, sa * sb * cc - ca * sc], -1),
            np.stack([-sb, cb * sc, cb * cc], -1),
        ],
        -2,
    )


def abc_from_matrix(R: ArrayLike) -> FloatArray:
    """KUKA angles ``(a, b, c)`` with ``R = Rz(a) Ry(b) Rx(c)`` (radians).

    Ranges: ``a, c`` in ``(-pi, pi]``, ``b`` in ``[-pi/2, pi/2]``. At gimbal lock
    (``|cos b| < 1e-12``, i.e. ``b = +-90`` degrees) only ``a - c`` (``b = +90``) or
    ``a + c`` (``b = -90``) is determined; then ``c = 0``. ``b`` and ``c`` are
    computed from ``a`` (as in Eigen's ``eulerAngles``), so the reconstructed
    matrix matches ``R`` to rounding error also near gimbal lock.

    Parameters
    ----------
    R
        Rotation matrices, shape ``(..., 3, 3)``.

    Returns
    -------
    numpy.ndarray
        Angles ``(..., 3)`` in radians.
    """
    R = _mat3(R, "R")
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20 = R[..., 2, 0]
    gimbal = np.hypot(r00, r10) < _GIMBAL_EPS
    a = np.where(gimbal, np.arctan2(-r01, r11), np.arctan2(r10, r00))
    ca, sa = np.cos(a), np.sin(a)
    # Rz(a)^T R = Ry(b) Rx(c): row 0 = [cb, sb sc, sb cc], row 1 = [0, cc, -sc].
    b = np.arctan2(-r20, ca * r00 + sa * r10)
    c = np.arctan2(sa * r02 - ca * r12, ca * r11 - sa * r01)
    return np.stack([a, b, c], -1)


def check_rotation(R: ArrayLike, tol: float = ROTATION_TOL, name: str = "rotation") -> FloatArray:
    """Validate rotation matrices: orthonormal within ``tol`` and right-handed.

    Parameters
    ----------
    R
        Candidate matrices, shape ``(..., 3, 3)``.
    tol
        Largest accepted entry of ``|R^T R - I|`` (default :data:`ROTATION_TOL`).
    name
        What to call the matrix in the error message.

    Returns
    -------
    numpy.ndarray
        ``R`` as a float array (unchanged).

    Raises
    ------
    RotationError
        If a matrix is not finite, not orthonormal within ``tol`` or has ``det <= 0``.
    """
    R = np.asarray(R, dtype=float)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise RotationError(
            f"{name} must be a 3x3 matrix (or a stack of them), got shape {R.shape}"
        )
    # Entries of R^T R - I and det R from column dot/triple products: several times
    # faster than batched matmul / np.linalg.det on large stacks of 3x3 matrices.
    c0, c1, c2 = R[..., 0], R[..., 1], R[..., 2]

    def dot(u: FloatArray, v: FloatArray) -> FloatArray:
        return np.einsum("...i,...i->...", u, v)

    err = np.maximum.reduce(
        [
            np.abs(dot(c0, c0) - 1.0),
            np.abs(dot(c1, c1) - 1.0),
            np.abs(dot(c2, c2) - 1.0),
            np.abs(dot(c0, c1)),
            np.abs(dot(c0, c2)),
            np.abs(dot(c1, c2)),
        ]
    )
    det = dot(c0, np.cross(c1, c2))
    bad = ~np.isfinite(err) | (err > tol) | ~(det > 0)
    if np.any(bad):
        idx = tuple(int(i) for i in np.argwhere(np.atleast_1d(bad))[0])
        e = float(np.atleast_1d(err)[idx])
        d = float(np.atleast_1d(det)[idx])
        where = "" if R.ndim == 2 else f" at index {idx}"
        raise RotationError(
            f"{name}{where} is not a rotation matrix: max |R^T R - I| = {e:.3g}"
            f" (tolerance {tol:g}), det = {d:.9g} (expected +1)"
        )
    return R


def exp_so3_one(x: float, y: float, z: float) -> FloatArray:
    """Rotation matrix of one rotation vector ``(x, y, z)`` (rad), Rodrigues' formula.

    :func:`exp_so3` for a control loop: scalar arithmetic, no input checks.
    """
    th2 = x * x + y * y + z * z
    if th2 < _SMALL_ANGLE**2:
        a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
        b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
        c = 1.0 - th2 / 2.0 + th2 * th2 / 24.0
    else:
        th = math.sqrt(th2)
        a, b, c = math.sin(th) / th, (1.0 - math.cos(th)) / th2, math.cos(th)
    bx, by = b * x, b * y
    return np.array(
        [
            [c + bx * x, bx * y - a * z, bx * z + a * y],
            [bx * y + a * z, c + by * y, by * z - a * x],
            [bx * z - a * y, by * z + a * x, c + b * z * z],
        ]
    )


def log_so3_one(R: FloatArray) -> FloatArray:
    """Rotation vector (rad) of one rotation matrix, :func:`log_so3` for a control loop.

    Scalar arithmetic below 90 degrees (no input checks); :func:`log_so3` beyond.
    """
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    c = 0.5 * (r00 + r11 + r22 - 1.0)
    if c < 0.0:
        return log_so3(R)
    x, y, z = 0.5 * (r21 - r12), 0.5 * (r02 - r20), 0.5 * (r10 - r01)
    s = math.sqrt(x * x + y * y + z * z)
    k = math.atan2(s, c) / s if s > 1e-8 else 1.0 + s * s / 6.0
    return np.array([k * x, k * y, k * z])
