"""Robot-vendor pose conventions, both directions, in the vendors' units.

=======  ==========================================  ====================================
Vendor   Representation                              Units / convention
=======  ==========================================  ====================================
KUKA     ``X Y Z A B C``                             mm, degrees, ``R = Rz(A) Ry(B) Rx(C)``
ABB      ``[[x, y, z], [q1, q2, q3, q4]]``           mm, unit quaternion w-first, ``q1 >= 0``
UR       ``p[x, y, z, rx, ry, rz]``                  metres, rotation vector (rad)
=======  ==========================================  ====================================

Every function takes one pose or a batch and returns the same: a single
:class:`~fabflow.transforms.pose.Pose` gives arrays of shape ``(6,)`` (KUKA, UR)
or ``(3,)`` + ``(4,)`` (ABB); a batch of shape ``(N,)`` gives ``(N, 6)`` etc.
Inputs with a wrong shape or non-finite values raise
:class:`~fabflow.errors.InputError`; an ABB quaternion farther than 1e-6 from
unit norm raises :class:`~fabflow.transforms.errors.QuaternionError` (closer
ones are normalized).

KUKA ranges: ``A, C`` in ``(-180, 180]``, ``B`` in ``[-90, 90]``; at ``B = +-90``
(gimbal lock) ``C = 0``. UR rotation vectors have angle in ``[0, pi]``; at exactly
180 degrees ``+axis * pi`` and ``-axis * pi`` are the same rotation and either may
be returned.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.transforms.pose import Pose
from fabflow.transforms.so3 import (
    QUATERNION_TOL,
    abc_from_matrix,
    exp_so3,
    matrix_from_abc,
    matrix_from_quat,
)

FloatArray = NDArray[np.float64]

MM_PER_M = 1000.0


def _values(values: ArrayLike, n: int, what: str) -> FloatArray:
    try:
        a = np.asarray(values, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{what}: expected numbers, got {values!r}") from exc
    if a.ndim == 0 or a.shape[-1] != n:
        raise InputError(f"{what}: expected {n} values per pose, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{what}: values must be finite (no NaN or infinity)")
    return a


def _as_pose(pose: Pose | ArrayLike) -> Pose:
    """A :class:`Pose` as is; anything else is read as 4x4 matrices (validated)."""
    return pose if isinstance(pose, Pose) else Pose.from_matrix(pose)


def to_kuka_xyzabc(pose: Pose | ArrayLike) -> FloatArray:
    """KUKA ``[X, Y, Z, A, B, C]`` (mm, degrees) of pose(s), shape ``(..., 6)``.

    ``pose`` is a :class:`Pose` or 4x4 matrices (``(4, 4)`` / ``(..., 4, 4)``, metres),
    as for the other ``to_*`` functions.
    """
    pose = _as_pose(pose)
    abc = np.degrees(abc_from_matrix(pose.R))
    return np.concatenate([pose.t * MM_PER_M, abc], axis=-1)


def from_kuka_xyzabc(values: ArrayLike) -> Pose:
    """Pose(s) from KUKA ``[X, Y, Z, A, B, C]`` (mm, degrees), shape ``(6,)`` or ``(..., 6)``."""
    v = _values(values, 6, "KUKA X Y Z A B C")
    a, b, c = np.radians(v[..., 3]), np.radians(v[..., 4]), np.radians(v[..., 5])
    return Pose._trusted(matrix_from_abc(a, b, c), v[..., :3] / MM_PER_M)


def to_abb_pose(pose: Pose | ArrayLike) -> tuple[FloatArray, FloatArray]:
    """ABB ``([x, y, z], [q1, q2, q3, q4])``: mm and unit quaternion (w first, ``q1 >= 0``).

    Returns
    -------
    tuple of numpy.ndarray
        Positions ``(..., 3)`` in mm and quaternions ``(..., 4)``.
    """
    pose = _as_pose(pose)
    return pose.t * MM_PER_M, pose.quat


def from_abb_pose(
    position: ArrayLike, quaternion: ArrayLike, *, tol: float = QUATERNION_TOL
) -> Pose:
    """Pose(s) from an ABB position (mm) and quaternion ``[q1, q2, q3, q4]`` (w first).

    Parameters
    ----------
    position
        ``(3,)`` or ``(..., 3)`` in mm.
    quaternion
        ``(4,)`` or ``(..., 4)``; normalized when within ``tol`` of unit norm.

    Raises
    ------
    QuaternionError
        If a quaternion is farther than ``tol`` from unit norm.
    """
    p = _values(position, 3, "ABB position [x, y, z]")
    q = _values(quaternion, 4, "ABB orientation [q1, q2, q3, q4]")
    return Pose._trusted(matrix_from_quat(q, tol), p / MM_PER_M)


def to_ur_pose(pose: Pose | ArrayLike) -> FloatArray:
    """UR ``p[x, y, z, rx, ry, rz]`` (metres, rotation vector in rad), shape ``(..., 6)``."""
    pose = _as_pose(pose)
    return np.concatenate([np.array(pose.t, dtype=float), pose.rotvec], axis=-1)


def from_ur_pose(values: ArrayLike) -> Pose:
    """Pose(s) from UR ``[x, y, z, rx, ry, rz]`` (metres, rad), shape ``(6,)`` or ``(..., 6)``.

    Any rotation-vector length is accepted (angles above pi wrap as usual).
    """
    v = _values(values, 6, "UR pose p[x, y, z, rx, ry, rz]")
    return Pose._trusted(exp_so3(v[..., 3:]), v[..., :3].copy())
