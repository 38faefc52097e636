"""Rigid fits of matched 3D points: the batch-capable building blocks of registration.

:func:`kabsch` (weighted, reflection-safe), :func:`refine_registration`
(Gauss-Newton on the full Mahalanobis cost, batched), :func:`optimize_registration`
(the constrained SLSQP form of paper 001), :func:`register_leveled` (4 DOF: a
levelled instrument, as in a free-station set-up), and the input and geometry
checks they share (:func:`as_points`, :func:`check_geometry`). Metres throughout.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from scipy import optimize

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.small_linalg import (
    best_rotation,
    eigvalsh3,
    exp_rotvec,
    solve_spd6,
)
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


def principal_spreads(points: np.ndarray) -> np.ndarray:
    """RMS spreads ``(..., 3)`` of point sets ``(..., n, 3)`` along principal axes, largest first.

    The square roots of the eigenvalues of the sets' scatter matrices over
    ``n`` (metres; the singular values of the centred points over ``sqrt(n)``).
    """
    n = points.shape[-2]
    centred = points - points.mean(axis=-2, keepdims=True)
    scatter = np.swapaxes(centred, -1, -2) @ centred
    return np.sqrt(np.maximum(eigvalsh3(scatter)[..., ::-1], 0.0) / n)


def degenerate(spreads: np.ndarray) -> np.ndarray:
    """Whether point sets with these :func:`principal_spreads` cannot fix a rigid pose."""
    return (spreads[..., 1] < MIN_SPREAD) | (spreads[..., 1] < COLLINEAR_RATIO * spreads[..., 0])


def check_geometry(points: np.ndarray, name: str = "points") -> None:
    """Refuse point sets that cannot fix a rigid pose: fewer than 3, or (nearly) collinear.

    Raises
    ------
    LocalizationError
        When the second principal spread of ``points`` ((n, 3), metres) is below
        :data:`MIN_SPREAD` or below :data:`COLLINEAR_RATIO` times the first.
    """
    check_geometries((points,), (name,))


def check_geometries(point_sets: tuple[np.ndarray, ...], names: tuple[str, ...]) -> None:
    """:func:`check_geometry` of several ``(n, 3)`` sets of the same size in one call.

    The first set that fails (in the order given) raises.
    """
    n = point_sets[0].shape[0]
    if n < 3:
        raise LocalizationError(f"{names[0]}: need at least 3 points to fix a pose, got {n}")
    stacked = point_sets[0] if len(point_sets) == 1 else np.stack(point_sets)
    spreads = principal_spreads(stacked).reshape(len(point_sets), 3)
    bad = degenerate(spreads)
    if bad.any():
        k = int(np.argmax(bad))
        s = spreads[k]
        raise LocalizationError(
            f"{names[k]}: the {n} points are (nearly) collinear or coincident "
            f"(principal spreads {s[0]:.4g} m, {s[1]:.3g} m); the rotation about their "
            "line is undetermined. Use points that span a plane."
        )


def kabsch(
    points_base: np.ndarray, points_world: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rigid fit ``points_world ~ R @ points_base + t`` (no checks).

    Reflection-safe Kabsch/Umeyama without scale, batch-capable (the rotation
    from :func:`fabflow.positioning.small_linalg.best_rotation`).

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
    if weights is None:
        p0 = P.mean(axis=-2)
        m0 = M.mean(axis=-2)
        H = np.swapaxes(P - p0[..., None, :], -1, -2) @ (M - m0[..., None, :])
    else:
        w = np.asarray(weights, dtype=float)
        w = w / w.sum(axis=-1, keepdims=True)
        p0 = (w[..., None, :] @ P)[..., 0, :]
        m0 = (w[..., None, :] @ M)[..., 0, :]
        H = np.swapaxes(P - p0[..., None, :], -1, -2) @ ((M - m0[..., None, :]) * w[..., None])
    R = best_rotation(H)
    return R, m0 - (R @ p0[..., None])[..., 0]


def kabsch_leave_one_out(
    points_base: np.ndarray, points_world: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`kabsch` of all the points and of every set with one point left out, at once.

    Leaving point ``k`` out moves the weighted centroids by ``-f_k (p_k - p0)``
    and ``-f_k (m_k - m0)``, ``f_k = w_k / (1 - w_k)`` (weights summing to 1),
    and changes the cross-covariance by the rank-one downdate
    ``-f_k (p_k - p0)(m_k - m0)^T``; the ``n + 1`` rotations then come from one
    stack of 3x3 problems (:func:`~fabflow.positioning.small_linalg.best_rotation`)
    instead of ``n`` fits.

    Parameters
    ----------
    points_base, points_world
        ``(..., n, 3)`` corresponding points (metres), n >= 4.
    weights
        ``(..., n)`` positive weights.

    Returns
    -------
    R, t
        ``(..., n + 1, 3, 3)`` and ``(..., n + 1, 3)``: index 0 the fit of all the
        points, index ``1 + k`` the fit without point ``k``.
    """
    w = weights / weights.sum(axis=-1, keepdims=True)
    p0 = (w[..., None, :] @ points_base)[..., 0, :]
    m0 = (w[..., None, :] @ points_world)[..., 0, :]
    Pc = points_base - p0[..., None, :]
    Mc = points_world - m0[..., None, :]
    H = np.swapaxes(Pc, -1, -2) @ (Mc * w[..., None])
    f = w / (1.0 - w)
    fP = f[..., None] * Pc
    stack = np.concatenate(
        [H[..., None, :, :], H[..., None, :, :] - fP[..., :, None] * Mc[..., None, :]], axis=-3
    )
    R = best_rotation(stack)
    p_c = np.concatenate([p0[..., None, :], p0[..., None, :] - fP], axis=-2)
    m_c = np.concatenate([m0[..., None, :], m0[..., None, :] - f[..., None] * Mc], axis=-2)
    return R, m_c - (R @ p_c[..., None])[..., 0]


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


def _jacobian_maps() -> tuple[np.ndarray, np.ndarray]:
    """Constant parts of the ``3 x 7`` block ``[J_i | v_i]`` of a point (:func:`normal_equations`).

    ``J_i = [I | -skew(q_i)]``: the identity, and the ``(3, 21)`` linear map from
    ``q_i`` to the flattened block.
    """
    base = np.zeros((3, 7))
    base[:, :3] = np.eye(3)
    of_q = np.zeros((3, 3, 7))
    # -skew(q)[a, b] = sign * q[c]
    for a, b, c, sign in (
        (0, 1, 2, 1),
        (0, 2, 1, -1),
        (1, 0, 2, -1),
        (1, 2, 0, 1),
        (2, 0, 1, 1),
        (2, 1, 0, -1),
    ):
        of_q[c, a, 3 + b] = sign
    return base, of_q.reshape(3, 21)


_JACOBIAN_BASE, _JACOBIAN_OF_Q = _jacobian_maps()


class NormalEquations(NamedTuple):
    """The linearised point fit at a pose: what the Gauss-Newton step and the tests need.

    Shapes for ``n`` points and batch dimensions ``...``; metres, world frame.

    Attributes
    ----------
    q
        ``(..., n, 3)`` the base points rotated into the world, ``R p_i``.
    v
        ``(..., n, 3)`` residuals ``m_i - (R p_i + t)`` (measured minus fitted).
    WJ
        ``(..., n, 3, 6)`` information times Jacobian, ``W_i J_i`` (see :func:`point_jacobians`).
    Wv
        ``(..., n, 3)`` ``W_i v_i``.
    N
        ``(..., 6, 6)`` normal matrix ``sum_i J_i^T W_i J_i``.
    g
        ``(..., 6)`` ``sum_i J_i^T W_i v_i``.
    """

    q: np.ndarray
    v: np.ndarray
    WJ: np.ndarray
    Wv: np.ndarray
    N: np.ndarray
    g: np.ndarray


def normal_equations(
    R: np.ndarray, t: np.ndarray, P: np.ndarray, M: np.ndarray, W: np.ndarray
) -> NormalEquations:
    """The :class:`NormalEquations` of ``m_i ~ R p_i + t`` with information matrices ``W``.

    ``R (..., 3, 3)``, ``t (..., 3)``, ``P, M (..., n, 3)`` (metres), ``W (..., n, 3, 3)``
    (1/m^2). The Jacobian and the residual go through the products as one
    ``3 x 7`` block per point, so the whole system is two batched matrix products.
    """
    q = P @ np.swapaxes(R, -1, -2)
    Jv = (q @ _JACOBIAN_OF_Q).reshape(*q.shape, 7)
    Jv += _JACOBIAN_BASE
    v = M - q - t[..., None, :]
    Jv[..., 6] = v
    WJv = W @ Jv
    sums = (np.swapaxes(Jv[..., :6], -1, -2) @ WJv).sum(axis=-3)
    return NormalEquations(q, v, WJv[..., :6], WJv[..., 6], sums[..., :6], sums[..., 6])


def gauss_newton(
    R: np.ndarray,
    t: np.ndarray,
    P: np.ndarray,
    M: np.ndarray,
    W: np.ndarray,
    max_iter: int = 5,
    tol: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`refine_registration` with the iterations of every problem of the batch.

    Each problem stops at its own convergence (a batch gives each problem what
    it alone would give). Returns ``R``, ``t`` and the ``(...)`` integer array of
    iterations.
    """
    batch = R.shape[:-2]
    iters = np.zeros(batch, dtype=int)
    active = np.ones(batch, dtype=bool)
    for _ in range(max_iter):
        eq = normal_equations(R, t, P, M, W)
        delta = solve_spd6(eq.N, eq.g)
        R_new = exp_rotvec(delta[..., 3:]) @ R
        t_new = t + delta[..., :3]
        iters += active
        if not batch:
            R, t = R_new, t_new
        else:
            R = np.where(active[..., None, None], R_new, R)
            t = np.where(active[..., None], t_new, t)
        active = active & (np.einsum("...i,...i->...", delta, delta) >= tol**2)
        if not active.any():
            break
    return R, t, iters


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
    ``t <- t + d``); a problem stops once its step is below ``tol``. Returns the
    refined ``R``, ``t`` and the most iterations any problem used.
    """
    R, t, iters = gauss_newton(
        np.asarray(R, dtype=float), np.asarray(t, dtype=float), P, M, W, max_iter, tol
    )
    return R, t, int(iters.max(initial=0))


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
