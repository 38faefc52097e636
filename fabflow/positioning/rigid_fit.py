"""Rigid fits of matched 3D points: the batch-capable building blocks of registration.

:func:`kabsch` (weighted, reflection-safe), :func:`refine_registration`
(Gauss-Newton on the full Mahalanobis cost, batched), :func:`optimize_registration`
(the constrained SLSQP form of paper 001), :func:`register_leveled` (4 DOF: a
levelled instrument, as in a free-station set-up), and the input and geometry
checks they share (:func:`as_points`, :func:`check_geometry`). Metres throughout.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import optimize

from fabflow.errors import InputError, LocalizationError
from fabflow.transforms.so3 import exp_so3

COLLINEAR_RATIO = 1e-3
"""Smallest accepted ratio of the second to the first principal spread of the points."""
MIN_SPREAD = 1e-4
"""Smallest accepted second principal spread (RMS, metres) of the points."""


def as_points(a: Any, name: str, n: int | None = None) -> np.ndarray:
    try:
        p = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be an (n, 3) array of numbers") from None
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{name} must have shape (n, 3), got {p.shape}")
    if n is not None and p.shape[0] != n:
        raise InputError(f"{name} has {p.shape[0]} points, expected {n} (one per base point)")
    if not np.all(np.isfinite(p)):
        row = int(np.flatnonzero(~np.all(np.isfinite(p), axis=1))[0])
        raise InputError(f"{name} row {row} is not finite")
    return p


def check_geometry(points: np.ndarray, name: str = "points") -> None:
    """Refuse point sets that cannot fix a rigid pose: fewer than 3, or (nearly) collinear.

    Raises
    ------
    LocalizationError
        When the second principal spread of ``points`` ((n, 3), metres) is below
        :data:`MIN_SPREAD` or below :data:`COLLINEAR_RATIO` times the first.
    """
    n = points.shape[0]
    if n < 3:
        raise LocalizationError(f"{name}: need at least 3 points to fix a pose, got {n}")
    centred = points - points.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False) / np.sqrt(n)
    if s[1] < MIN_SPREAD or s[1] < COLLINEAR_RATIO * s[0]:
        raise LocalizationError(
            f"{name}: the {n} points are (nearly) collinear or coincident "
            f"(principal spreads {s[0]:.4g} m, {s[1]:.3g} m); the rotation about their "
            "line is undetermined. Use points that span a plane."
        )


def _det3(A: np.ndarray) -> np.ndarray:
    """Determinants of ``(..., 3, 3)`` matrices (cheaper than ``np.linalg.det`` on tiny ones)."""
    return (
        A[..., 0, 0] * (A[..., 1, 1] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 1])
        - A[..., 0, 1] * (A[..., 1, 0] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 0])
        + A[..., 0, 2] * (A[..., 1, 0] * A[..., 2, 1] - A[..., 1, 1] * A[..., 2, 0])
    )


def kabsch(
    points_base: np.ndarray, points_world: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rigid fit ``points_world ~ R @ points_base + t`` (no checks).

    Reflection-safe Kabsch/Umeyama without scale, batch-capable.

    Parameters
    ----------
    points_base, points_world
        ``(..., n, 3)`` corresponding points (metres).
    weights
        ``(..., n)`` non-negative weights, or None for equal weights.

    Returns
    -------
    R, t
        ``(..., 3, 3)`` rotations and ``(..., 3)`` translations.
    """
    P = np.asarray(points_base, dtype=float)
    M = np.asarray(points_world, dtype=float)
    if P.ndim == 2:
        # single problem: plain matrix products, no einsum or batch bookkeeping
        if weights is None:
            p0 = P.mean(axis=0)
            m0 = M.mean(axis=0)
            H = (P - p0).T @ (M - m0)
        else:
            w = np.asarray(weights, dtype=float) / np.sum(weights)
            p0 = w @ P
            m0 = w @ M
            H = (P - p0).T @ ((M - m0) * w[:, None])
        U, _, Vt = np.linalg.svd(H)
        R = (U @ Vt).T
        (a, b, c), (d, e, f), (g, h, i) = R.tolist()
        if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0:
            Vt[2] = -Vt[2]
            R = (U @ Vt).T
        return R, m0 - R @ p0
    w = np.ones(P.shape[:-1]) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum(axis=-1, keepdims=True)
    p0 = np.einsum("...n,...ni->...i", w, P)
    m0 = np.einsum("...n,...ni->...i", w, M)
    H = np.einsum("...n,...ni,...nj->...ij", w, P - p0[..., None, :], M - m0[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    # R = V diag(1, 1, det(V U^T)) U^T: flipping the weakest axis avoids a reflection
    s = np.sign(_det3(U) * _det3(Vt))
    s = np.where(s == 0, 1.0, s)
    Vt = Vt.copy()
    Vt[..., 2, :] *= s[..., None]
    R = np.swapaxes(U @ Vt, -1, -2)
    t = m0 - np.einsum("...ij,...j->...i", R, p0)
    return R, t


def point_jacobians(R: np.ndarray, points_base: np.ndarray) -> np.ndarray:
    """``(..., n, 3, 6)`` derivative of the fitted world points by ``[d, r]`` (fabflow convention).

    ``R`` is ``(..., 3, 3)``, ``points_base`` ``(..., n, 3)``.
    """
    q = np.einsum("...ij,...nj->...ni", R, points_base)
    J = np.zeros((*q.shape, 6))
    J[..., :3] = np.eye(3)
    # right block -skew(q), filled in place (this runs in every Gauss-Newton step)
    J[..., 0, 4], J[..., 0, 5] = q[..., 2], -q[..., 1]
    J[..., 1, 3], J[..., 1, 5] = -q[..., 2], q[..., 0]
    J[..., 2, 3], J[..., 2, 4] = q[..., 1], -q[..., 0]
    return J


def normal_matrices(J: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Per-point ``J^T W J``, ``(..., n, 6, 6)``."""
    return np.einsum("...nki,...nkl,...nlj->...nij", J, W, J)


def refine_registration(
    R: np.ndarray,
    t: np.ndarray,
    P: np.ndarray,
    M: np.ndarray,
    W: np.ndarray,
    max_iter: int = 5,
    tol: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Gauss-Newton on ``sum_i e_i^T W_i e_i``, ``e_i = R p_i + t - m_i``, from ``(R, t)``.

    Batch-capable: ``R (..., 3, 3)``, ``t (..., 3)``, ``P, M (..., n, 3)`` (metres),
    ``W (..., n, 3, 3)`` information matrices (inverse point covariances, 1/m^2).
    Steps are applied in fabflow's error convention (``R <- Exp(r) R``,
    ``t <- t + d``). Returns the refined ``R``, ``t`` and the iterations used.
    """
    it = 0
    while it < max_iter:
        it += 1
        e = np.einsum("...ij,...nj->...ni", R, P) + t[..., None, :] - M
        J = point_jacobians(R, P)
        A = normal_matrices(J, W).sum(axis=-3)
        b = np.einsum("...nki,...nkl,...nl->...i", J, W, e)
        delta = -np.linalg.solve(A, b[..., None])[..., 0]
        R = exp_so3(delta[..., 3:]) @ R
        t = t + delta[..., :3]
        if np.max(np.einsum("...i,...i->...", delta, delta)) < tol**2:
            break
    return R, t, it


def optimize_registration(
    points_base: np.ndarray,
    points_world: np.ndarray,
    weights: np.ndarray | None = None,
    T_init: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The paper's eqs 7-8: constrained least squares over origin ``O`` and axes ``X``, ``Y``.

    Minimises ``sum w_i |O + P_ix X + P_iy Y + P_iz (X x Y) - M_i|^2`` subject to
    ``X . Y = 0``, ``|X| = |Y| = 1`` with SciPy's SLSQP and analytic gradients.

    Parameters
    ----------
    points_base, points_world
        ``(n, 3)`` points (metres), already validated.
    weights
        ``(n,)`` weights or None.
    T_init
        Initial pose. Without one, the best of eight headings about the world z
        axis (each with its least-squares origin) starts the search, which
        plays the role of the paper's "initial guess close to the solution".

    Returns
    -------
    R, t, iterations
    """
    w = np.ones(len(points_base)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    # both point sets are centred first (a change of variables of O only): with
    # site coordinates tens of metres from the origin SLSQP otherwise crawls
    p0, m0 = w @ points_base, w @ points_world
    P = points_base - p0
    M = points_world - m0
    if T_init is None:
        yaw = np.arange(8) * (np.pi / 4)
        Rs = exp_so3(np.outer(yaw, [0.0, 0.0, 1.0]))
        e = np.einsum("kij,nj->kni", Rs, P) - M
        R0 = Rs[int(np.argmin(np.einsum("n,kni,kni->k", w, e, e)))]
    else:
        R0 = T_init[:3, :3]
    x0 = np.concatenate([np.zeros(3), R0[:, 0], R0[:, 1]])
    px, py, pz = P[:, 0], P[:, 1], P[:, 2]

    def residual(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        origin, X, Y = x[:3], x[3:6], x[6:]
        e = origin + np.outer(px, X) + np.outer(py, Y) + np.outer(pz, np.cross(X, Y)) - M
        return e, X, Y

    def fun(x: np.ndarray) -> float:
        e, _, _ = residual(x)
        return float(np.einsum("n,ni,ni->", w, e, e))

    def jac(x: np.ndarray) -> np.ndarray:
        e, X, Y = residual(x)
        we = w[:, None] * e
        gO = 2 * we.sum(axis=0)
        gX = 2 * (px @ we + pz @ np.cross(Y, we))
        gY = 2 * (py @ we + pz @ np.cross(we, X))
        return np.concatenate([gO, gX, gY])

    def cons(x: np.ndarray) -> np.ndarray:
        X, Y = x[3:6], x[6:]
        return np.array([X @ Y, X @ X - 1.0, Y @ Y - 1.0])

    def cons_jac(x: np.ndarray) -> np.ndarray:
        X, Y = x[3:6], x[6:]
        z = np.zeros(3)
        return np.array(
            [
                np.concatenate([z, Y, X]),
                np.concatenate([z, 2 * X, z]),
                np.concatenate([z, z, 2 * Y]),
            ]
        )

    res = optimize.minimize(
        fun,
        x0,
        jac=jac,
        method="SLSQP",
        constraints=[{"type": "eq", "fun": cons, "jac": cons_jac}],
        options={"ftol": 1e-15, "maxiter": 200},
    )
    origin, X, Y = res.x[:3], res.x[3:6], res.x[6:]
    U, _, Vt = np.linalg.svd(np.column_stack([X, Y, np.cross(X, Y)]))
    R = U @ Vt
    return R, m0 + origin - R @ p0, int(res.nit)


def register_leveled(
    points_local: np.ndarray, points_world: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form fit of a levelled frame: heading about z plus translation (4 DOF).

    A total station's compensator levels it, so a free-station setup only
    solves for its position and the orientation of its Hz circle. The weighted
    least-squares heading is ``atan2(sum w (x_l y_w - y_l x_w), sum w (x_l x_w + y_l y_w))``
    over centred coordinates. Batch-capable.

    Parameters
    ----------
    points_local, points_world
        ``(..., n, 3)`` points in the levelled local frame and in the world (metres), n >= 2.
    weights
        ``(..., n)`` weights, or None.

    Returns
    -------
    R, t
        ``(..., 3, 3)`` rotations about z and ``(..., 3)`` translations.
    """
    P = np.asarray(points_local, dtype=float)
    M = np.asarray(points_world, dtype=float)
    w = np.ones(P.shape[:-1]) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum(axis=-1, keepdims=True)
    p0 = np.einsum("...n,...ni->...i", w, P)
    m0 = np.einsum("...n,...ni->...i", w, M)
    a = P - p0[..., None, :]
    b = M - m0[..., None, :]
    s = np.einsum("...n,...n->...", w, a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])
    c = np.einsum("...n,...n->...", w, a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1])
    yaw = np.arctan2(s, c)
    R = exp_so3(yaw[..., None] * np.array([0.0, 0.0, 1.0]))
    t = m0 - np.einsum("...ij,...j->...i", R, p0)
    return R, t
