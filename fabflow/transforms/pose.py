"""The immutable, batch-capable rigid pose type.

A :class:`Pose` holds one pose or an array of poses (any batch shape) as a
rotation ``R`` (``(..., 3, 3)``) and a translation ``t`` (``(..., 3)``, metres).
Name instances ``T_a_b`` (pose of frame ``b`` in frame ``a``):
``T_world_base @ T_base_tool == T_world_tool`` and
``T_a_b.apply(p_b) == p_a``.

Validation: rotation matrices given to the constructor, :meth:`Pose.from_matrix`
and :meth:`Pose.from_rt` are checked for orthonormality
(``max |R^T R - I| <= 1e-6`` and ``det R > 0``, see
:data:`fabflow.transforms.so3.ROTATION_TOL`) and raise
:class:`~fabflow.transforms.errors.RotationError` otherwise; accepted matrices
are stored unchanged. Quaternions are normalized when within 1e-6 of unit norm
and rejected with :class:`~fabflow.transforms.errors.QuaternionError` otherwise.
Results of operations on valid poses (compose, inverse, interpolate) are not
re-validated.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.transforms.errors import DegenerateFrameError
from fabflow.transforms.so3 import (
    QUATERNION_TOL,
    ROTATION_TOL,
    check_rotation,
    exp_so3,
    log_so3,
    matrix_from_quat,
    quat_from_matrix,
)

FloatArray = NDArray[np.float64]


def _frozen(a: FloatArray) -> FloatArray:
    a = np.ascontiguousarray(a, dtype=float)
    a.flags.writeable = False
    return a


def _translation(t: ArrayLike | None, batch: tuple[int, ...]) -> FloatArray:
    if t is None:
        return np.zeros((*batch, 3))
    a = np.array(t, dtype=float)  # a copy: a Pose must not share memory with its inputs
    if a.ndim == 0 or a.shape[-1] != 3:
        raise InputError(f"translation must have shape (..., 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError("translation contains NaN or infinite values")
    return a


def _apply_single(R: FloatArray, t: FloatArray | None, p: FloatArray) -> FloatArray:
    """``p @ R.T + t`` for one rotation and points ``(..., 3)``.

    Computed as ``R @ p.T`` (a 3 x 3 by 3 x N product): ``p @ R.T`` (N x 3 by
    3 x 3) is several times slower with multi-threaded OpenBLAS on a loaded
    machine. For ``(N, 3)`` input the result is a transposed (Fortran-ordered)
    view, which saves a copy.
    """
    flat = p.reshape(-1, 3)
    out = R @ flat.T
    if t is not None:
        out += t[:, None]
    return out.T if p.ndim == 2 else out.T.reshape(p.shape)


class Pose:
    """One rigid pose or a batch of them (rotation + translation in metres).

    Parameters
    ----------
    R
        Rotation matrices, ``(3, 3)`` or ``(..., 3, 3)``; validated (see module docstring).
    t
        Translations in metres, ``(3,)`` or ``(..., 3)``; default zero. ``R`` and ``t``
        broadcast against each other.
    tol
        Orthonormality tolerance for ``R``.

    Notes
    -----
    Instances are immutable (the stored arrays are read-only). ``a @ b`` composes
    (batch shapes broadcast), ``pose.inverse()`` inverts, ``pose.apply(points)``
    transforms points from the child into the parent frame.
    """

    __slots__ = ("_R", "_t")
    __array_ufunc__ = None  # keep numpy from hijacking ``ndarray @ Pose``

    _R: FloatArray
    _t: FloatArray

    def __init__(self, R: ArrayLike, t: ArrayLike | None = None, *, tol: float = ROTATION_TOL):
        R = np.array(check_rotation(R, tol))  # copy: never share memory with the caller
        t = _translation(t, R.shape[:-2])
        batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
        object.__setattr__(self, "_R", _frozen(np.broadcast_to(R, (*batch, 3, 3))))
        object.__setattr__(self, "_t", _frozen(np.broadcast_to(t, (*batch, 3))))

    @classmethod
    def _trusted(cls, R: FloatArray, t: FloatArray) -> Pose:
        """Build without validation (for results of operations on valid poses)."""
        p = object.__new__(cls)
        batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
        if R.shape[:-2] != batch:
            R = np.broadcast_to(R, (*batch, 3, 3))
        if t.shape[:-1] != batch:
            t = np.broadcast_to(t, (*batch, 3))
        object.__setattr__(p, "_R", _frozen(R))
        object.__setattr__(p, "_t", _frozen(t))
        return p

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("Pose is immutable")

    def __reduce__(self) -> tuple[Any, ...]:
        # pickling/deepcopy (e.g. dask workers) would otherwise go through __setattr__
        return (Pose._trusted, (np.array(self._R), np.array(self._t)))

    # ------------------------------------------------------------------ constructors

    @classmethod
    def identity(cls, shape: int | tuple[int, ...] = ()) -> Pose:
        """Identity pose(s) with the given batch shape."""
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        return cls._trusted(
            np.broadcast_to(np.eye(3), (*shape, 3, 3)).copy(), np.zeros((*shape, 3))
        )

    @classmethod
    def from_matrix(cls, m: ArrayLike, *, tol: float = ROTATION_TOL) -> Pose:
        """Pose(s) from homogeneous matrices ``(4, 4)`` or ``(..., 4, 4)`` (metres).

        Raises
        ------
        InputError
            If the shape is wrong or the bottom row is not ``[0, 0, 0, 1]``.
        RotationError
            If the rotation block is not orthonormal within ``tol``.
        """
        m = np.asarray(m, dtype=float)
        if m.ndim < 2 or m.shape[-2:] != (4, 4):
            raise InputError(f"pose matrix must have shape (4, 4) or (..., 4, 4), got {m.shape}")
        if not np.allclose(m[..., 3, :], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=tol):
            raise InputError("pose matrix bottom row must be [0, 0, 0, 1]")
        return cls(m[..., :3, :3], m[..., :3, 3], tol=tol)

    @classmethod
    def from_rt(
        cls, R: ArrayLike, t: ArrayLike | None = None, *, tol: float = ROTATION_TOL
    ) -> Pose:
        """Same as the constructor: rotation matrices ``R`` and translations ``t`` (m)."""
        return cls(R, t, tol=tol)

    @classmethod
    def from_quat(
        cls, q: ArrayLike, t: ArrayLike | None = None, *, tol: float = QUATERNION_TOL
    ) -> Pose:
        """Pose(s) from quaternions ``(w, x, y, z)`` and translations (m).

        Quaternions within ``tol`` of unit norm are normalized; others raise
        :class:`~fabflow.transforms.errors.QuaternionError`.
        """
        R = matrix_from_quat(q, tol)
        return cls._trusted(R, _translation(t, R.shape[:-2]))

    @classmethod
    def from_rotvec(cls, rotvec: ArrayLike, t: ArrayLike | None = None) -> Pose:
        """Pose(s) from rotation vectors ``angle * axis`` (rad) and translations (m)."""
        rv = np.asarray(rotvec, dtype=float)
        if rv.ndim == 0 or rv.shape[-1] != 3 or not np.all(np.isfinite(rv)):
            raise InputError(f"rotation vector must be finite with shape (..., 3), got {rv.shape}")
        R = exp_so3(rv)
        return cls._trusted(R, _translation(t, R.shape[:-2]))

    @classmethod
    def from_euler(
        cls, seq: str, angles: ArrayLike, t: ArrayLike | None = None, *, degrees: bool = False
    ) -> Pose:
        """Pose(s) from Euler angles in a named convention (``scipy`` semantics).

        Parameters
        ----------
        seq
            Axis sequence as in :meth:`scipy.spatial.transform.Rotation.from_euler`:
            upper case = intrinsic (rotating axes), lower case = extrinsic (fixed
            axes). KUKA ABC is ``"ZYX"`` with angles ``(A, B, C)``.
        angles
            Angles ``(..., len(seq))``.
        t
            Translations in metres.
        degrees
            Angles in degrees instead of radians.
        """
        ang = np.asarray(angles, dtype=float)
        if ang.ndim == 0 or ang.shape[-1] != len(seq):
            raise InputError(f"Euler angles for {seq!r} must have shape (..., {len(seq)})")
        try:
            from scipy.spatial.transform import Rotation  # only here: keeps imports light

            rot = Rotation.from_euler(seq, ang.reshape(-1, len(seq)), degrees=degrees)
        except ValueError as exc:
            raise InputError(f"invalid Euler sequence {seq!r}: {exc}") from exc
        R = rot.as_matrix().reshape((*ang.shape[:-1], 3, 3))
        return cls._trusted(R, _translation(t, R.shape[:-2]))

    @classmethod
    def from_frame(cls, origin: ArrayLike, x_axis_point: ArrayLike, xy_point: ArrayLike) -> Pose:
        """Frame from three points (three-point frame teaching / total-station setup).

        The x axis points from ``origin`` to ``x_axis_point``; ``xy_point`` lies in
        the xy plane on the positive-y side; z completes a right-handed frame. The
        result is ``T_parent_frame`` where the points are given in the parent frame.

        Parameters
        ----------
        origin, x_axis_point, xy_point
            Points in the parent frame (m), each ``(3,)`` or ``(..., 3)``.

        Raises
        ------
        DegenerateFrameError
            If the points coincide or are (nearly) collinear.
        """
        o = np.asarray(origin, dtype=float)
        px = np.asarray(x_axis_point, dtype=float)
        pxy = np.asarray(xy_point, dtype=float)
        for name, a in (("origin", o), ("x_axis_point", px), ("xy_point", pxy)):
            if a.ndim == 0 or a.shape[-1] != 3 or not np.all(np.isfinite(a)):
                raise InputError(f"{name} must be finite with shape (..., 3), got {a.shape}")
        vx = px - o
        vxy = pxy - o
        lx = np.linalg.norm(vx, axis=-1)
        scale = np.maximum(lx, np.linalg.norm(vxy, axis=-1))
        z = np.cross(vx, vxy)
        lz = np.linalg.norm(z, axis=-1)
        # |x| * |xy| * sin(angle) small relative to the point spread -> collinear
        bad = (lx <= 1e-12 * np.maximum(scale, 1.0)) | (lz <= 1e-9 * np.maximum(scale, 1e-12) ** 2)
        if np.any(bad):
            raise DegenerateFrameError(
                "the three frame points coincide or are collinear; expected an origin,"
                " a point on the +x axis and a point in the xy plane off that axis"
            )
        ex = vx / lx[..., None]
        ez = z / lz[..., None]
        ey = np.cross(ez, ex)
        R = np.stack([ex, ey, ez], axis=-1)
        return cls._trusted(R, np.broadcast_to(o, R.shape[:-1]).copy())

    @classmethod
    def stack(cls, poses: list[Pose] | tuple[Pose, ...]) -> Pose:
        """Stack single poses (or equal-shaped batches) along a new first axis."""
        if not poses:
            raise ValueError("Pose.stack needs at least one pose")
        return cls._trusted(np.stack([p._R for p in poses]), np.stack([p._t for p in poses]))

    # ------------------------------------------------------------------ exporters

    @property
    def R(self) -> FloatArray:
        """Rotation matrices ``(..., 3, 3)`` (read-only)."""
        return self._R

    @property
    def t(self) -> FloatArray:
        """Translations in metres ``(..., 3)`` (read-only)."""
        return self._t

    @property
    def matrix(self) -> FloatArray:
        """Homogeneous matrices: ``(4, 4)`` for one pose, ``(..., 4, 4)`` for a batch."""
        T = np.zeros((*self.shape, 4, 4))
        T[..., :3, :3] = self._R
        T[..., :3, 3] = self._t
        T[..., 3, 3] = 1.0
        return T

    @property
    def quat(self) -> FloatArray:
        """Unit quaternions ``(w, x, y, z)`` with ``w >= 0``, shape ``(..., 4)``."""
        return quat_from_matrix(self._R)

    @property
    def rotvec(self) -> FloatArray:
        """Rotation vectors (rad), angle in ``[0, pi]``, shape ``(..., 3)``."""
        return log_so3(self._R)

    def euler(self, seq: str, *, degrees: bool = False) -> FloatArray:
        """Euler angles in a named convention (see :meth:`from_euler`), ``(..., len(seq))``.

        Computed by scipy; at gimbal lock the third angle is set to zero (scipy's
        warning about it is suppressed). For KUKA ABC prefer
        :func:`fabflow.transforms.to_kuka_xyzabc`.
        """
        from scipy.spatial.transform import Rotation  # only here: keeps imports light

        rot = Rotation.from_matrix(self._R.reshape(-1, 3, 3))
        try:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="Gimbal lock detected")
                ang = rot.as_euler(seq, degrees=degrees)
        except ValueError as exc:
            raise InputError(f"invalid Euler sequence {seq!r}: {exc}") from exc
        return ang.reshape((*self.shape, len(seq)))

    @property
    def shape(self) -> tuple[int, ...]:
        """Batch shape (``()`` for a single pose)."""
        return self._t.shape[:-1]

    @property
    def is_batch(self) -> bool:
        """Whether this holds a batch (batch shape not ``()``)."""
        return self._t.ndim > 1

    def __len__(self) -> int:
        if not self.is_batch:
            raise TypeError("a single Pose has no len()")
        return self._t.shape[0]

    def __getitem__(self, index: Any) -> Pose:
        if not self.is_batch:
            raise TypeError("a single Pose cannot be indexed")
        R = self._R[index]
        t = self._t[index]
        if R.ndim < 2 or R.shape[-2:] != (3, 3) or t.shape[-1:] != (3,):
            raise IndexError("index must select along the batch dimensions only")
        return Pose._trusted(R, t)

    def __iter__(self) -> Iterator[Pose]:
        for i in range(len(self)):
            yield self[i]

    def __repr__(self) -> str:
        if not self.is_batch:
            rv = np.round(self.rotvec, 6).tolist()
            return f"Pose(t={np.round(self._t, 6).tolist()}, rotvec={rv})"
        return f"Pose(batch shape={self.shape})"

    # ------------------------------------------------------------------ operations

    def __matmul__(self, other: Pose) -> Pose:
        if not isinstance(other, Pose):
            return NotImplemented
        R1, t1 = self._R, self._t
        R = R1 @ other._R
        if R1.ndim == 2:
            t = other._t @ R1.T + t1
        else:
            t = np.einsum("...ij,...j->...i", R1, other._t) + t1
        return Pose._trusted(R, t)

    def compose(self, other: Pose) -> Pose:
        """``self @ other``: ``T_a_b.compose(T_b_c) = T_a_c``."""
        return self @ other

    def inverse(self) -> Pose:
        """Inverse pose(s): ``T_a_b.inverse() = T_b_a``."""
        Rt = np.swapaxes(self._R, -1, -2)
        if Rt.ndim == 2:
            t = -(Rt @ self._t)
        else:
            t = -np.einsum("...ij,...j->...i", Rt, self._t)
        return Pose._trusted(Rt.copy(), t)

    def apply(self, points: ArrayLike) -> FloatArray:
        """Transform points from the child into the parent frame (m).

        Parameters
        ----------
        points
            ``(3,)`` or ``(N, 3)`` (any leading dims) for a single pose. For a batch
            pose, leading dims broadcast with the batch shape (a batch of N poses
            with ``(N, 3)`` points transforms point i by pose i).

        Returns
        -------
        numpy.ndarray
            Transformed points, shape of the broadcast batch + ``(3,)``.
        """
        p = np.asarray(points, dtype=float)
        if p.ndim == 0 or p.shape[-1] != 3:
            raise InputError(f"points must have shape (..., 3), got {p.shape}")
        if not self.is_batch:
            return _apply_single(self._R, self._t, p)
        return np.einsum("...ij,...j->...i", self._R, p) + self._t

    def apply_rotation(self, vectors: ArrayLike) -> FloatArray:
        """Rotate direction vectors (no translation); broadcasting as :meth:`apply`."""
        v = np.asarray(vectors, dtype=float)
        if not self.is_batch:
            return _apply_single(self._R, None, v)
        return np.einsum("...ij,...j->...i", self._R, v)

    def interpolate(self, other: Pose, s: ArrayLike) -> Pose:
        """Interpolate towards ``other``: slerp for rotation, linear for translation.

        Parameters
        ----------
        other
            End pose(s); batch shape broadcasts with ``self``.
        s
            Fraction(s) in ``[0, 1]`` (0 -> ``self``, 1 -> ``other``), broadcast with
            the batch shape (numpy rules): single poses with ``s`` of shape ``(K,)``
            give K poses; a batch of N with ``s`` of shape ``(N,)`` gives one
            fraction per pose; ``a[:, None]`` with ``s`` of shape ``(K,)`` gives N x K.

        Returns
        -------
        Pose
            ``R = R0 Exp(s Log(R0^T R1))`` (shortest arc) and ``t = (1 - s) t0 + s t1``.
        """
        s = np.asarray(s, dtype=float)
        rel = log_so3(np.swapaxes(self._R, -1, -2) @ other._R)
        R = self._R @ exp_so3(rel * s[..., None])
        t = self._t + (other._t - self._t) * s[..., None]
        return Pose._trusted(R, t)

    def distance(self, other: Pose) -> tuple[FloatArray, FloatArray]:
        """Translation distance (m) and rotation angle (rad, in ``[0, pi]``) to ``other``.

        Returns
        -------
        tuple of numpy.ndarray
            ``(|t1 - t0|, angle of R0^T R1)``, each of the broadcast batch shape.
        """
        d = np.linalg.norm(other._t - self._t, axis=-1)
        ang = np.linalg.norm(log_so3(np.swapaxes(self._R, -1, -2) @ other._R), axis=-1)
        return d, ang

    def allclose(self, other: Pose, atol: float = 1e-9) -> bool:
        """Whether all matrices agree with ``other``'s within ``atol`` (broadcasting)."""
        return bool(
            np.allclose(self._R, other._R, rtol=0.0, atol=atol)
            and np.allclose(self._t, other._t, rtol=0.0, atol=atol)
        )
