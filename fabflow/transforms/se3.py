"""Rigid transforms (SE(3)) as 4x4 numpy matrices, batch-capable, and error propagation.

A pose ``T_a_b`` (shape ``(..., 4, 4)``) maps points from frame ``b`` to frame
``a``: ``p_a = T_a_b @ [p_b, 1]``; ``T_a_b @ T_b_c = T_a_c``. Translations are
metres.

Covariance convention (the one of :mod:`fabflow.positioning.result`): a 6x6
covariance over the error ``delta = [dx, dy, dz, rx, ry, rz]`` of a pose
``T_a_b = [R, t]`` where the true pose is ``[Exp(r) @ R, t + d]``: translation
error and small rotation both expressed in the parent frame ``a``, the rotation
taken about the origin of ``b``. This is *not* the usual left-twist
perturbation ``Exp(xi) @ T``; the two are related by
``xi = [[I, skew(t)], [0, I]] @ delta`` (:func:`twist_from_error`). The
propagation functions below (:func:`compose_jacobians`, :func:`inverse_jacobian`,
:func:`compose_covariance`, :func:`inverse_covariance`) all use fabflow's
convention.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.transforms.so3 import exp_so3, log_so3, skew

FloatArray = NDArray[np.float64]


def _mat4(T: ArrayLike, name: str = "T") -> FloatArray:
    a = np.asarray(T, dtype=float)
    if a.ndim < 2 or a.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must have shape (..., 4, 4), got {a.shape}")
    return a


def make_T(R: ArrayLike, t: ArrayLike) -> FloatArray:
    """Homogeneous matrices from rotations and translations.

    Parameters
    ----------
    R
        Rotation matrices, shape ``(..., 3, 3)`` (not validated here).
    t
        Translations in metres, shape ``(..., 3)``; broadcast against ``R``.

    Returns
    -------
    numpy.ndarray
        Poses, shape ``(..., 4, 4)``.
    """
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros((*batch, 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def inv_T(T: ArrayLike) -> FloatArray:
    """Inverse of rigid transforms: ``inv_T(T_a_b) = T_b_a``.

    Parameters
    ----------
    T
        Poses, shape ``(..., 4, 4)`` (rigid; the bottom row is assumed ``[0, 0, 0, 1]``).

    Returns
    -------
    numpy.ndarray
        Inverse poses, shape ``(..., 4, 4)``.
    """
    T = _mat4(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_T(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def compose_T(*Ts: ArrayLike) -> FloatArray:
    """Chain poses left to right: ``compose_T(T_a_b, T_b_c, T_c_d) = T_a_d``.

    Parameters
    ----------
    *Ts
        One or more poses, each ``(..., 4, 4)``; batch dimensions broadcast.

    Returns
    -------
    numpy.ndarray
        The composed pose(s), shape ``(..., 4, 4)``.
    """
    if not Ts:
        raise ValueError("compose_T needs at least one pose")
    out = _mat4(Ts[0])
    for T in Ts[1:]:
        out = out @ _mat4(T)
    return out


def relative_T(T_w_a: ArrayLike, T_w_b: ArrayLike) -> FloatArray:
    """Relative pose ``T_a_b = inv(T_w_a) @ T_w_b`` of two poses in a common frame."""
    return inv_T(T_w_a) @ _mat4(T_w_b)


def apply_T(T: ArrayLike, points: ArrayLike) -> FloatArray:
    """Transform points: ``p_a = R @ p_b + t`` for ``T = T_a_b``.

    Parameters
    ----------
    T
        One pose ``(4, 4)`` or poses ``(..., 4, 4)``.
    points
        Points in the child frame (metres), shape ``(..., 3)``. With a single pose,
        any number of leading dimensions (e.g. ``(N, 3)``). With a batch of poses,
        the batch dimensions of ``T`` and ``points`` broadcast (use
        ``T[:, None]`` with points ``(N, M, 3)`` to apply each pose to M points).

    Returns
    -------
    numpy.ndarray
        Points in the parent frame, shape of the broadcast batch + ``(3,)``.
    """
    T = _mat4(T)
    p = np.asarray(points, dtype=float)
    if p.ndim == 0 or p.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., 3), got {p.shape}")
    if T.ndim == 2:
        # R @ p.T (3x3 by 3xN) instead of p @ R.T: much faster with threaded BLAS
        out = T[:3, :3] @ p.reshape(-1, 3).T
        out += T[:3, 3, None]
        return out.T if p.ndim == 2 else out.T.reshape(p.shape)
    return np.einsum("...ij,...j->...i", T[..., :3, :3], p) + T[..., :3, 3]


def apply_R(R: ArrayLike, vectors: ArrayLike) -> FloatArray:
    """Rotate vectors (directions, no translation); broadcasting as :func:`apply_T`."""
    R = np.asarray(R, dtype=float)
    v = np.asarray(vectors, dtype=float)
    if R.ndim == 2:
        out = R @ v.reshape(-1, 3).T
        return out.T if v.ndim == 2 else out.T.reshape(v.shape)
    return np.einsum("...ij,...j->...i", R, v)


def adjoint(T: ArrayLike) -> FloatArray:
    """SE(3) adjoint ``[[R, skew(t) R], [0, R]]`` for twists ordered ``[v, w]``.

    ``Ad(T)`` maps a body twist (``T @ Exp(xi_b)``) to a spatial twist
    (``Exp(xi_s) @ T``): ``xi_s = Ad(T) @ xi_b``. Under fabflow's covariance
    convention (module docstring) a body-frame error maps to the parent-frame error
    with ``blockdiag(R, R)`` instead (:func:`error_from_body_twist`), and
    ``Ad(T) = twist_from_error(T) @ error_from_body_twist(T)``.

    Parameters
    ----------
    T
        Poses, shape ``(..., 4, 4)``.

    Returns
    -------
    numpy.ndarray
        Adjoint matrices, shape ``(..., 6, 6)``.
    """
    T = _mat4(T)
    R = T[..., :3, :3]
    A = np.zeros((*T.shape[:-2], 6, 6))
    A[..., :3, :3] = R
    A[..., 3:, 3:] = R
    A[..., :3, 3:] = skew(T[..., :3, 3]) @ R
    return A


def error_from_body_twist(T: ArrayLike) -> FloatArray:
    """6x6 map from a body-frame error (``T @ Exp(xi_b)``) to fabflow's parent-frame error.

    To first order ``T @ Exp([v, w]) = [Exp(R w) R, t + R v]``, so the map is
    ``blockdiag(R, R)``. Use it to express a covariance estimated in the child
    frame (e.g. a body-frame ICP Hessian) in fabflow's convention:
    ``C = M @ C_body @ M.T``.
    """
    T = _mat4(T)
    R = T[..., :3, :3]
    M = np.zeros((*T.shape[:-2], 6, 6))
    M[..., :3, :3] = R
    M[..., 3:, 3:] = R
    return M


def twist_from_error(T: ArrayLike) -> FloatArray:
    """6x6 map from fabflow's error ``[d, r]`` to the left (spatial) twist ``[v, w]``.

    To first order ``[Exp(r) R, t + d] = Exp(xi) @ T`` with
    ``xi = [d + skew(t) r, r]``.
    """
    T = _mat4(T)
    M = np.zeros((*T.shape[:-2], 6, 6))
    M[..., :3, :3] = np.eye(3)
    M[..., 3:, 3:] = np.eye(3)
    M[..., :3, 3:] = skew(T[..., :3, 3])
    return M


def perturb(T: ArrayLike, delta: ArrayLike) -> FloatArray:
    """Apply errors in fabflow's convention: ``[Exp(r) @ R, t + d]``.

    Parameters
    ----------
    T
        Poses, shape ``(..., 4, 4)``.
    delta
        Errors ``[dx, dy, dz, rx, ry, rz]`` (m, rad), shape ``(..., 6)``; broadcast
        against ``T`` (e.g. one pose and ``(N, 6)`` samples).

    Returns
    -------
    numpy.ndarray
        Perturbed poses, shape ``(..., 4, 4)``.
    """
    T = _mat4(T)
    delta = np.asarray(delta, dtype=float)
    return make_T(exp_so3(delta[..., 3:]) @ T[..., :3, :3], T[..., :3, 3] + delta[..., :3])


def pose_error(T_est: ArrayLike, T_true: ArrayLike) -> FloatArray:
    """Error ``[d, r]`` of ``T_est`` w.r.t. ``T_true`` in fabflow's convention (inverse of perturb).

    ``d = t_true - t_est``, ``r = Log(R_true @ R_est^T)``, so
    ``perturb(T_est, pose_error(T_est, T_true)) == T_true``.
    """
    T_est = _mat4(T_est, "T_est")
    T_true = _mat4(T_true, "T_true")
    dR = T_true[..., :3, :3] @ np.swapaxes(T_est[..., :3, :3], -1, -2)
    return np.concatenate([T_true[..., :3, 3] - T_est[..., :3, 3], log_so3(dR)], -1)


def compose_jacobians(T_a_b: ArrayLike, T_b_c: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """First-order Jacobians of ``T_a_c = T_a_b @ T_b_c`` in fabflow's error convention.

    With errors ``delta_ab`` (in frame a) and ``delta_bc`` (in frame b),
    ``delta_ac = J_ab @ delta_ab + J_bc @ delta_bc`` where
    ``J_ab = [[I, -skew(R_ab t_bc)], [0, I]]`` and ``J_bc = blockdiag(R_ab, R_ab)``.

    Returns
    -------
    tuple of numpy.ndarray
        ``(J_ab, J_bc)``, each ``(..., 6, 6)``.
    """
    T_a_b = _mat4(T_a_b, "T_a_b")
    T_b_c = _mat4(T_b_c, "T_b_c")
    R_ab = T_a_b[..., :3, :3]
    lever = np.einsum("...ij,...j->...i", R_ab, T_b_c[..., :3, 3])
    batch = np.broadcast_shapes(T_a_b.shape[:-2], T_b_c.shape[:-2])
    J_ab = np.zeros((*batch, 6, 6))
    J_ab[..., :3, :3] = np.eye(3)
    J_ab[..., 3:, 3:] = np.eye(3)
    J_ab[..., :3, 3:] = -skew(lever)
    J_bc = np.zeros((*batch, 6, 6))
    J_bc[..., :3, :3] = R_ab
    J_bc[..., 3:, 3:] = R_ab
    return J_ab, J_bc


def inverse_jacobian(T_a_b: ArrayLike) -> FloatArray:
    """First-order Jacobian of ``T_b_a = inv(T_a_b)`` in fabflow's error convention.

    ``delta_ba = [[-R^T, -R^T skew(t)], [0, -R^T]] @ delta_ab`` (shape ``(..., 6, 6)``).
    """
    T_a_b = _mat4(T_a_b, "T_a_b")
    Rt = np.swapaxes(T_a_b[..., :3, :3], -1, -2)
    J = np.zeros((*T_a_b.shape[:-2], 6, 6))
    J[..., :3, :3] = -Rt
    J[..., 3:, 3:] = -Rt
    J[..., :3, 3:] = -Rt @ skew(T_a_b[..., :3, 3])
    return J


def compose_covariance(
    T_a_b: ArrayLike, C_a_b: ArrayLike | None, T_b_c: ArrayLike, C_b_c: ArrayLike | None
) -> FloatArray:
    """Covariance of ``T_a_c = T_a_b @ T_b_c`` from independent edge covariances.

    Parameters
    ----------
    T_a_b, T_b_c
        Poses, ``(..., 4, 4)``.
    C_a_b, C_b_c
        6x6 covariances in fabflow's convention (``None`` = exact), ``(..., 6, 6)``.

    Returns
    -------
    numpy.ndarray
        ``C_a_c = J_ab C_a_b J_ab^T + J_bc C_b_c J_bc^T``, shape ``(..., 6, 6)``.
    """
    J_ab, J_bc = compose_jacobians(T_a_b, T_b_c)
    C = np.zeros(J_ab.shape)
    if C_a_b is not None:
        C = C + J_ab @ np.asarray(C_a_b, dtype=float) @ np.swapaxes(J_ab, -1, -2)
    if C_b_c is not None:
        C = C + J_bc @ np.asarray(C_b_c, dtype=float) @ np.swapaxes(J_bc, -1, -2)
    return C


def inverse_covariance(T_a_b: ArrayLike, C_a_b: ArrayLike) -> FloatArray:
    """Covariance of ``T_b_a = inv(T_a_b)`` (fabflow's convention), shape ``(..., 6, 6)``."""
    J = inverse_jacobian(T_a_b)
    return J @ np.asarray(C_a_b, dtype=float) @ np.swapaxes(J, -1, -2)


def point_covariance(T_a_b: ArrayLike, C_a_b: ArrayLike, points_b: ArrayLike) -> FloatArray:
    """3x3 covariance (m^2) of points ``p_a = T_a_b p_b`` from the pose covariance.

    With fabflow's error ``[d, r]``: ``p_a' = Exp(r) R p_b + t + d``, so to first order
    ``J = [I, -skew(R p_b)]`` and ``C_p = J C_a_b J^T``. Use it to turn a base pose
    uncertainty into the position uncertainty of targets.

    Parameters
    ----------
    T_a_b
        Pose(s) ``(..., 4, 4)``.
    C_a_b
        Covariance(s) ``(..., 6, 6)`` in fabflow's convention.
    points_b
        Points in frame ``b`` (m), ``(..., 3)``; broadcast with the pose batch.

    Returns
    -------
    numpy.ndarray
        Covariances ``(..., 3, 3)`` in frame ``a``.
    """
    T_a_b = _mat4(T_a_b, "T_a_b")
    C = np.asarray(C_a_b, dtype=float)
    p = np.asarray(points_b, dtype=float)
    lever = np.einsum("...ij,...j->...i", T_a_b[..., :3, :3], p)
    J = np.zeros((*lever.shape[:-1], 3, 6))
    J[..., :, :3] = np.eye(3)
    J[..., :, 3:] = -skew(lever)
    return J @ C @ np.swapaxes(J, -1, -2)


def exp_T(delta: ArrayLike) -> FloatArray:
    """Pose ``[Exp(r), d]`` of an error vector ``[d, r]``: ``perturb(identity, delta)``."""
    delta = np.asarray(delta, dtype=float)
    return make_T(exp_so3(delta[..., 3:]), delta[..., :3])
