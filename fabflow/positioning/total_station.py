"""Robot base localization with a robotic total station (paper 001, eqs 1-8).

A prism on the robot's tool is moved to known points ``p_i`` of the robot base
frame (from forward kinematics); the total station measures each one, giving
``m_i`` in the world. The base pose ``T_world_base`` is the rigid motion taking
the ``p_i`` onto the ``m_i``.

Solvers
-------
- :func:`register_points`: the arbitrary-point localization (eqs 7-8). Closed
  form by weighted Kabsch/Umeyama (reflection-safe); with per-point covariances
  (a total station's are needle-shaped along the line of sight) a few
  Gauss-Newton steps then minimise the full Mahalanobis cost. ``method="optimize"``
  solves the paper's constrained problem over ``(O, X, Y)`` with SLSQP instead.
  Either way the result carries the 6x6 covariance (fabflow convention, see
  :mod:`fabflow.positioning.result`), residuals, RMSE and a leave-one-out test
  for a single bad prism reading.
- :func:`three_point_localization` / :func:`localize_three_point`: eqs 1-6 for
  the points ``P1``, ``P1 + d x``, ``P1 + d y``.
- :func:`kabsch`, :func:`refine_registration`, :func:`register_leveled`: the
  batch-capable building blocks (the last one fits a levelled instrument,
  4 DOF, as in a free-station set-up).

Entry points
------------
- :func:`localize_files` / :func:`localize_observations`: measured readings
  (CSV or Leica GSI) against robot points (``fabflow localize total-station``).
- :func:`localize_station`: the simulated instrument used by ``fabflow build``
  and the simulator.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from scipy import optimize, special
from scipy.spatial import cKDTree

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.point_selection import (
    ClearanceRules,
    Workspace,
    avoid_obstacles,
    boxes_from_elements,
    clear_mask,
    optimal_points,
)
from fabflow.positioning.polar import (
    ARCSEC,
    Instrument,
    Observations,
    make_instrument,
    polar_covariance,
    polar_to_cartesian,
    simulate_polar,
    to_world,
)
from fabflow.positioning.result import BasePose
from fabflow.positioning.ts_io import read_observations, read_robot_points
from fabflow.project import TotalStationSetup
from fabflow.transforms.se3 import apply_T, compose_covariance, inv_T, make_T, perturb
from fabflow.transforms.so3 import exp_so3, log_so3, matrix_from_abc

if TYPE_CHECKING:
    from fabflow.design.elements import Element
    from fabflow.project import Project

COLLINEAR_RATIO = 1e-3
"""Smallest accepted ratio of the second to the first principal spread of the points."""
MIN_SPREAD = 1e-4
"""Smallest accepted second principal spread (RMS, metres) of the points."""


@dataclass(frozen=True, eq=False)
class OutlierTest:
    """Leave-one-out test for one bad prism reading.

    Each point is predicted from the fit to all the others; the prediction error
    is normalised by its predicted covariance. With known measurement
    covariances the statistic is chi-square with 3 degrees of freedom; with the
    noise level estimated from the residuals it is F(3, 3(n-1)-6).

    Attributes
    ----------
    index
        The most suspicious point (largest statistic).
    flagged
        Whether that point fails the test at level ``alpha / n``.
    statistics
        ``(n,)`` test statistic per point.
    threshold
        Critical value the statistics are compared to.
    p_value
        p-value of the most suspicious point.
    loo_residuals
        ``(n, 3)`` measured minus predicted position of each point from the fit
        without it (world frame, metres).
    known_sigma
        True when the statistic used the given covariances (chi-square), False
        when the noise level came from the residuals (F).
    """

    index: int
    flagged: bool
    statistics: np.ndarray
    threshold: float
    p_value: float
    loo_residuals: np.ndarray
    known_sigma: bool

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible data."""
        return {
            "index": self.index,
            "flagged": self.flagged,
            "statistics": self.statistics.tolist(),
            "threshold": self.threshold,
            "p_value": self.p_value,
            "loo_residuals": self.loo_residuals.tolist(),
            "test": "chi2(3)" if self.known_sigma else "F(3, 3n-9)",
        }


@dataclass(frozen=True, eq=False)
class Registration:
    """Result of a point registration.

    Attributes
    ----------
    T_world_base
        4x4 estimated pose of the robot base in the world (metres).
    covariance
        6x6 covariance over ``[dx, dy, dz, rx, ry, rz]`` (fabflow convention).
    residuals
        ``(n, 3)`` measured minus fitted world positions of every point (metres),
        including a rejected one.
    rmse
        RMS of the 3D residual lengths of the points used in the fit (metres).
    method
        ``"closed_form"``, ``"optimize"`` or ``"three_point"``.
    variance_factor
        Weighted residual sum of squares over its degrees of freedom; about 1
        when the given covariances are right (NaN without redundancy).
    outlier_test
        The leave-one-out test, or None with fewer than 4 points.
    rejected
        Indices of points left out of the final fit.
    iterations
        Gauss-Newton or optimizer iterations.
    """

    T_world_base: np.ndarray
    covariance: np.ndarray
    residuals: np.ndarray
    rmse: float
    method: str
    variance_factor: float = float("nan")
    outlier_test: OutlierTest | None = None
    rejected: tuple[int, ...] = ()
    iterations: int = 0

    @property
    def n_points(self) -> int:
        """Number of points given (including rejected ones)."""
        return int(self.residuals.shape[0])

    def quality(self) -> dict[str, Any]:
        """Quality figures for :attr:`BasePose.quality`."""
        q: dict[str, Any] = {
            "solver": self.method,
            "n_points": self.n_points,
            "n_inliers": self.n_points - len(self.rejected),
            "rejected": list(self.rejected),
            "variance_factor": None
            if not np.isfinite(self.variance_factor)
            else float(self.variance_factor),
            "iterations": self.iterations,
        }
        if self.outlier_test is not None:
            q["outlier_test"] = self.outlier_test.to_dict()
        return q

    def to_base_pose(
        self, station: str | None = None, quality: dict[str, Any] | None = None
    ) -> BasePose:
        """The result as a :class:`~fabflow.positioning.result.BasePose` (``total_station``)."""
        return BasePose(
            T_world_base=self.T_world_base.copy(),
            covariance=self.covariance.copy(),
            method="total_station",
            residuals=self.residuals.copy(),
            rmse=self.rmse,
            station=station,
            quality={**self.quality(), **(quality or {})},
        )


# ------------------------------------------------------------------ validation


def _as_points(a: Any, name: str, n: int | None = None) -> np.ndarray:
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


# ------------------------------------------------------------------- solvers


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


def _jacobians(R: np.ndarray, points_base: np.ndarray) -> np.ndarray:
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


def _normal_matrices(J: np.ndarray, W: np.ndarray) -> np.ndarray:
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
        J = _jacobians(R, P)
        A = _normal_matrices(J, W).sum(axis=-3)
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


# --------------------------------------------------------------- registration


def _loo_test(
    P: np.ndarray,
    M: np.ndarray,
    W: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    known_sigma: bool,
    alpha: float,
) -> OutlierTest | None:
    """Leave-one-out prediction test over all points at once (see :class:`OutlierTest`)."""
    n = P.shape[0]
    if n < 4:
        return None
    idx = np.nonzero(~np.eye(n, dtype=bool))[1].reshape(n, n - 1)
    # each leave-one-out fit starts from the full fit: a few Gauss-Newton steps
    # reach its own optimum (the weighted Kabsch one when W is isotropic)
    Rs, ts, _ = refine_registration(
        np.broadcast_to(R, (n, 3, 3)), np.broadcast_to(t, (n, 3)), P[idx], M[idx], W[idx], 3
    )
    d = M - (np.einsum("nij,nj->ni", Rs, P) + ts)
    J = _jacobians(R, P)
    N = _normal_matrices(J, W)
    cov_without = np.linalg.inv(N.sum(axis=0) - N)
    C = np.linalg.inv(W) + np.einsum("nij,njk,nlk->nil", J, cov_without, J)
    stat = np.einsum("ni,ni->n", d, np.linalg.solve(C, d[..., None])[..., 0])
    level = alpha / n
    if known_sigma:
        threshold = float(special.chdtri(3, level))
        k = int(np.argmax(stat))
        p_value = float(special.chdtrc(3, stat[k]))
    else:
        dof = 3 * (n - 1) - 6
        e = np.einsum("nij,nkj->nki", Rs, P[idx]) + ts[:, None, :] - M[idx]
        ssr = np.einsum("nkij,nki,nkj->n", W[idx], e, e)
        stat = stat / (3.0 * np.maximum(ssr / dof, 1e-24))
        threshold = float(special.fdtri(3, dof, 1.0 - level))
        k = int(np.argmax(stat))
        p_value = float(special.fdtrc(3, dof, stat[k]))
    return OutlierTest(
        index=k,
        flagged=bool(stat[k] > threshold),
        statistics=stat,
        threshold=threshold,
        p_value=p_value,
        loo_residuals=d,
        known_sigma=known_sigma,
    )


def register_points(
    points_base: Any,
    points_world: Any,
    weights: Any = None,
    *,
    point_cov: Any = None,
    sigma: float | None = None,
    base_sigma: float = 0.0,
    method: Literal["closed_form", "optimize"] = "closed_form",
    reject_outlier: bool = False,
    alpha: float = 1e-3,
) -> Registration:
    """Localize the robot base from prism points known in the base frame and measured in the world.

    Parameters
    ----------
    points_base
        ``(n, 3)`` prism positions in the robot base frame (metres), n >= 3.
    points_world
        ``(n, 3)`` the same prisms measured in the world frame (metres).
    weights
        ``(n,)`` relative weights (used when ``point_cov`` is not given).
    point_cov
        ``(n, 3, 3)`` covariance of each measured point (m^2, world frame), e.g.
        from :func:`fabflow.positioning.polar.polar_covariance`. Makes the fit
        minimise the Mahalanobis cost and the covariance absolute.
    sigma
        Isotropic standard deviation of the measured points (metres) when
        ``point_cov`` is not given. Without either, the noise level is
        estimated from the residuals.
    base_sigma
        Isotropic standard deviation of the base-frame points (robot
        positioning error, metres), added to every point's covariance.
    method
        ``"closed_form"`` (weighted Kabsch, then Gauss-Newton on the full
        covariances) or ``"optimize"`` (the paper's SLSQP problem, eqs 7-8).
    reject_outlier
        Refit without the point the leave-one-out test flags (needs n >= 4, and
        the other points must not be collinear; otherwise it is only reported).
    alpha
        Significance level of the outlier test (Bonferroni-corrected over n).

    Returns
    -------
    Registration
        ``T_world_base``, ``covariance`` (6x6), ``residuals`` (n x 3), ``rmse``, ...

    Raises
    ------
    InputError
        Arrays of the wrong shape, non-finite values, bad weights.
    LocalizationError
        Fewer than 3 points, or collinear/coincident points.
    """
    P = _as_points(points_base, "points_base")
    M = _as_points(points_world, "points_world", n=P.shape[0])
    n = P.shape[0]
    check_geometry(P, "points_base")
    check_geometry(M, "points_world")
    if method not in ("closed_form", "optimize"):
        raise InputError(f"unknown method {method!r}; expected 'closed_form' or 'optimize'")
    known_sigma = point_cov is not None or sigma is not None
    if point_cov is not None:
        C = np.asarray(point_cov, dtype=float)
        if C.shape != (n, 3, 3) or not np.all(np.isfinite(C)):
            raise InputError(f"point_cov must be a finite ({n}, 3, 3) array, got {C.shape}")
        C = C + base_sigma**2 * np.eye(3)
        if np.any(np.linalg.eigvalsh(C)[:, 0] <= 0):
            raise InputError("point_cov must be positive definite for every point")
        w = 3.0 / np.trace(C, axis1=1, axis2=2)
    else:
        w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
        if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise InputError(f"weights must be {n} non-negative finite numbers, not all zero")
        s2 = (1.0 if sigma is None else sigma**2) + base_sigma**2
        # zero-weight points get a placeholder: they never enter the fit
        C = (s2 / np.where(w > 0, w, 1.0))[:, None, None] * np.eye(3)
    keep = w > 0
    if not keep.all():
        check_geometry(P[keep], "points_base with positive weight")
    W = np.zeros_like(C)
    W[keep] = np.linalg.inv(C[keep])

    def solve(sel: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        if method == "optimize":
            return optimize_registration(P[sel], M[sel], w[sel])
        R, t = kabsch(P[sel], M[sel], w[sel])
        if point_cov is not None:
            return refine_registration(R, t, P[sel], M[sel], W[sel])
        return R, t, 0

    R, t, iters = solve(keep)
    sel_idx = np.flatnonzero(keep)
    test = _loo_test(P[keep], M[keep], W[keep], R, t, known_sigma, alpha)
    rejected: tuple[int, ...] = tuple(int(i) for i in np.flatnonzero(~keep))
    if test is not None:
        test = OutlierTest(
            index=int(sel_idx[test.index]),
            flagged=test.flagged,
            statistics=_scatter(test.statistics, sel_idx, n, np.nan),
            threshold=test.threshold,
            p_value=test.p_value,
            loo_residuals=_scatter(test.loo_residuals, sel_idx, n, np.nan),
            known_sigma=test.known_sigma,
        )
        trial = keep.copy()
        trial[test.index] = False
        if reject_outlier and test.flagged and _spans_plane(P[trial]):
            keep = trial
            R, t, iters = solve(keep)
            rejected = tuple(int(i) for i in np.flatnonzero(~keep))

    J = _jacobians(R, P[keep])
    info = _normal_matrices(J, W[keep]).sum(axis=0)
    cov = np.linalg.inv(info)
    residuals = M - (P @ R.T + t)
    r_in = residuals[keep]
    dof = 3 * int(keep.sum()) - 6
    chi2 = float(np.einsum("ni,nij,nj->", r_in, W[keep], r_in))
    vf = chi2 / dof if dof > 0 else float("nan")
    if not known_sigma:
        # relative weights only: scale the covariance by the estimated variance
        cov = cov * (vf if dof > 0 else 0.0)
    return Registration(
        T_world_base=make_T(R, t),
        covariance=0.5 * (cov + cov.T),
        residuals=residuals,
        rmse=float(np.sqrt(np.mean(np.einsum("ni,ni->n", r_in, r_in)))),
        method=method,
        variance_factor=vf,
        outlier_test=test,
        rejected=rejected,
        iterations=iters,
    )


def _spans_plane(points: np.ndarray) -> bool:
    try:
        check_geometry(points)
    except LocalizationError:
        return False
    return True


def _scatter(values: np.ndarray, idx: np.ndarray, n: int, fill: float) -> np.ndarray:
    out = np.full((n, *values.shape[1:]), fill)
    out[idx] = values
    return out


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


# ------------------------------------------------------------------ three point


def three_point_base_points(p1: Any, d: float) -> np.ndarray:
    """The localization points of eqs 1-6 in the base frame: ``P1``, ``P1 + d x``, ``P1 + d y``."""
    p1 = np.asarray(p1, dtype=float)
    return p1 + np.array([[0.0, 0.0, 0.0], [d, 0.0, 0.0], [0.0, d, 0.0]])


def three_point_localization(
    points_world: np.ndarray, p2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs 1-6: base pose from the measured ``M1, M2, M3`` of ``P1, P1 + d x, P1 + d y``.

    ``X = M2 - M1``, ``Y = M3 - M1``, ``Z = X x Y`` (eq 1), normalised (eq 2);
    the paper leaves ``X`` and ``Y`` as measured, here ``Y`` is re-orthogonalised
    as ``Z x X`` so the result is a rotation. The origin is eq 3:
    ``O = M2 - P2x X - P2y Y - P2z Z``.

    Parameters
    ----------
    points_world
        ``(..., 3, 3)`` measured ``M1, M2, M3`` (metres, rows).
    p2
        ``(..., 3)`` the base-frame point ``P2 = P1 + d x``.

    Returns
    -------
    R, t
        ``(..., 3, 3)`` and ``(..., 3)``: the pose of the base in the world.
    """
    Mw = np.asarray(points_world, dtype=float)
    X = Mw[..., 1, :] - Mw[..., 0, :]
    Y = Mw[..., 2, :] - Mw[..., 0, :]
    Z = np.cross(X, Y)
    X = X / np.linalg.norm(X, axis=-1, keepdims=True)
    Z = Z / np.linalg.norm(Z, axis=-1, keepdims=True)
    Y = np.cross(Z, X)
    R = np.stack([X, Y, Z], axis=-1)
    p2 = np.asarray(p2, dtype=float)
    t = Mw[..., 1, :] - np.einsum("...ij,...j->...i", R, p2)
    return R, t


def localize_three_point(
    points_world: Any,
    p1: Any,
    d: float,
    point_cov: Any = None,
    base_sigma: float = 0.0,
) -> Registration:
    """Three-point localization (eqs 1-6) with first-order covariance.

    Parameters
    ----------
    points_world
        ``(3, 3)`` measured prism positions at ``P1``, ``P1 + d x``, ``P1 + d y`` (metres).
    p1
        ``(3,)`` the first point in the base frame (metres).
    d
        Step along the base x and y axes (metres, > 0).
    point_cov
        ``(3, 3, 3)`` covariances of the measured points (m^2); zero when None.
    base_sigma
        Robot positioning standard deviation (metres), added to each point.
    """
    M = _as_points(points_world, "points_world", n=3)
    if not d > 0:
        raise InputError(f"the three-point step d must be positive, got {d}")
    P = three_point_base_points(p1, d)
    check_geometry(M, "points_world")
    R, t = three_point_localization(M, P[1])
    C = np.zeros((3, 3, 3)) if point_cov is None else np.asarray(point_cov, dtype=float)
    C = C + base_sigma**2 * np.eye(3)
    # numerical Jacobian of [d, r] by the 9 measured coordinates (one batched call)
    eps = 1e-6
    Mp = np.repeat(M[None], 9, axis=0)
    Mp.reshape(9, 9)[np.arange(9), np.arange(9)] += eps
    Rp, tp = three_point_localization(Mp, P[1])
    dR = Rp @ R.T
    Jn = np.concatenate([tp - t, log_so3(dR)], axis=1).T / eps
    C9 = np.zeros((9, 9))
    for k in range(3):
        C9[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = C[k]
    cov = Jn @ C9 @ Jn.T
    residuals = M - (P @ R.T + t)
    return Registration(
        T_world_base=make_T(R, t),
        covariance=0.5 * (cov + cov.T),
        residuals=residuals,
        rmse=float(np.sqrt(np.mean(np.einsum("ni,ni->n", residuals, residuals)))),
        method="three_point",
    )


# --------------------------------------------------------------- observations


def localize_observations(
    observations: Observations,
    robot_ids: Sequence[str],
    robot_points: np.ndarray,
    instrument: Instrument,
    T_world_instrument: np.ndarray | None = None,
    base_sigma: float = 0.0,
    method: Literal["closed_form", "optimize"] = "closed_form",
    reject_outlier: bool = True,
) -> tuple[Registration, tuple[str, ...]]:
    """Register measured observations against robot points matched by point id.

    Parameters
    ----------
    observations
        Polar readings or coordinates from a file (:mod:`fabflow.positioning.ts_io`).
    robot_ids, robot_points
        Ids and ``(n, 3)`` prism positions in the base frame (metres).
    instrument
        Accuracy model used for the point covariances.
    T_world_instrument
        Instrument pose in the world (identity: the instrument frame is the world).
    base_sigma
        Robot positioning standard deviation (metres).
    method, reject_outlier
        As in :func:`register_points`.

    Returns
    -------
    registration, ids
        The result and the matched point ids in the order of its residuals.
    """
    seen: dict[str, int] = {}
    for k, pid in enumerate(observations.point_ids):
        if pid in seen:
            raise InputError(
                f"point id {pid!r} is observed twice",
                observations.source,
                f"line {observations.lines[k]}" if observations.lines else None,
            )
        seen[pid] = k
    index = {pid: k for k, pid in enumerate(robot_ids)}
    matched = [pid for pid in observations.point_ids if pid in index]
    if len(matched) < 3:
        raise LocalizationError(
            f"only {len(matched)} observed point id(s) match the robot points "
            f"(observed: {', '.join(observations.point_ids[:8])}; robot: "
            f"{', '.join(list(robot_ids)[:8])}); need at least 3",
            observations.source,
        )
    M_all, C_all = observations.points(instrument, T_world_instrument)
    rows = np.array([seen[pid] for pid in matched])
    P = np.asarray(robot_points, dtype=float)[[index[pid] for pid in matched]]
    reg = register_points(
        P,
        M_all[rows],
        point_cov=C_all[rows],
        base_sigma=base_sigma,
        method=method,
        reject_outlier=reject_outlier,
    )
    return reg, tuple(matched)


# ------------------------------------------------------------------ simulator


SAMPLE_TOLERANCE = 0.03
"""Largest distance (m) to a sampled prism position that counts as reachable (no closed-form IK)."""


@dataclass(frozen=True, eq=False)
class _Kinematics:
    """Reach test and forward kinematics of the prism for one robot and tool.

    Arms with closed-form IK reach a point with the tool pointing down (as in
    the reach maps). Machines without one (the 5-DOF BROKK) cannot choose the
    tool orientation, and a 360-degree prism does not need it: their reachable
    prism positions are a dense cloud of forward-kinematics samples of the
    joint space, and a point is reached by the nearest sample.
    """

    workspace: Workspace
    robot: Any
    T_flange_tool: np.ndarray
    samples_q: np.ndarray | None = None
    samples_tree: cKDTree | None = None

    def reachable(self, points: np.ndarray) -> np.ndarray:
        if self.samples_tree is not None:
            d, _ = self.samples_tree.query(points)
            return d <= SAMPLE_TOLERANCE
        T = self._tool_poses(points)
        _, valid = self.robot.ik_batch(T @ inv_T(self.T_flange_tool))
        return valid.any(axis=1)

    def _tool_poses(self, points: np.ndarray) -> np.ndarray:
        R_down = np.diag([1.0, -1.0, -1.0])
        return make_T(np.broadcast_to(R_down, (len(points), 3, 3)), points)

    def prism_points(self, points: np.ndarray) -> np.ndarray:
        """Joint values for the desired points, then the prism positions by FK."""
        if self.samples_tree is not None and self.samples_q is not None:
            d, k = self.samples_tree.query(points)
            bad = d > SAMPLE_TOLERANCE
            q = self.samples_q[k]
        else:
            T_base_flange = self._tool_poses(points) @ inv_T(self.T_flange_tool)
            q, valid = self.robot.ik_batch(T_base_flange)
            bad = ~valid.any(axis=1)
            q = q[np.arange(len(points)), np.argmax(valid, axis=1)]
        if bad.any():
            p = points[int(np.argmax(bad))]
            raise LocalizationError(
                f"{self.robot.name} cannot reach the localization point "
                f"({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f})"
            )
        return (self.robot.fk(q) @ self.T_flange_tool)[:, :3, 3]


@functools.lru_cache(maxsize=16)
def _joint_samples(model: str, T_flange_tool: tuple[float, ...]) -> tuple[np.ndarray, cKDTree]:
    from fabflow.robots import get_robot

    robot = get_robot(model)
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    q = np.random.default_rng(0).uniform(lo, hi, (40000, robot.dof))
    p = (robot.fk(q) @ np.asarray(T_flange_tool).reshape(4, 4))[:, :3, 3]
    return q, cKDTree(p)


def _kinematics(model: str, T_flange_tool: np.ndarray, z_min: float) -> _Kinematics:
    """Workspace (reach sphere about the shoulder) with the robot's exact reach test."""
    from fabflow.robots import get_robot

    robot = get_robot(model)
    shoulder = robot.frames(np.zeros(robot.dof))[1][:3, 3]
    ws = Workspace(center=(0.0, 0.0, float(shoulder[2])), reach=float(robot.reach), z_min=z_min)
    if robot.analytic_ik is None:
        q, tree = _joint_samples(model, tuple(np.asarray(T_flange_tool, float).ravel()))
        kin = _Kinematics(ws, robot, T_flange_tool, q, tree)
    else:
        kin = _Kinematics(ws, robot, T_flange_tool)
    # the top of the reach sphere is out of reach with the tool held down: cap the
    # workspace at the highest reachable point (in front of the robot, 5 cm margin)
    x = np.arange(0.1, ws.radius, 0.05)
    z = np.arange(z_min, ws.center[2] + ws.radius, 0.05)
    grid = np.stack(np.meshgrid(x, [0.0], z, indexing="ij"), axis=-1).reshape(-1, 3)
    ok = kin.reachable(grid)
    if not ok.any():
        raise LocalizationError(f"{model}: no prism position above z = {z_min} m is reachable")
    z_max = float(grid[ok, 2].max()) - 0.05
    return replace(kin, workspace=replace(ws, reachable=kin.reachable, z_max=z_max))


@functools.lru_cache(maxsize=64)
def _cached_optimal_points(n: int, workspace: Workspace) -> np.ndarray:
    # a fixed seed: the same workspace always gets the same points
    return optimal_points(n, replace(workspace, reachable=None), np.random.default_rng(0))


def setup_covariance(setup: TotalStationSetup) -> np.ndarray:
    """6x6 covariance of ``T_world_instrument`` from the set-up uncertainty fields.

    The instrument is levelled by its compensator, so only its position and
    its orientation about the vertical are uncertain.
    """
    s = setup.setup_sigma_mm * 1e-3
    a = setup.setup_sigma_arcsec * ARCSEC
    return np.diag([s * s, s * s, s * s, 0.0, 0.0, a * a])


def add_instrument_uncertainty(
    reg: Registration, T_world_instrument: np.ndarray, C_world_instrument: np.ndarray
) -> Registration:
    """Add the uncertainty of the instrument pose to a registration made in the world frame.

    The measured world points are ``T_world_instrument`` applied to the
    instrument's readings, so ``T_world_base = T_world_instrument @ T_instrument_base``
    and the set-up error propagates by :func:`~fabflow.transforms.se3.compose_covariance`.
    """
    if not np.any(C_world_instrument):
        return reg
    T_instrument_base = inv_T(T_world_instrument) @ reg.T_world_base
    C = compose_covariance(T_world_instrument, C_world_instrument, T_instrument_base, None)
    return replace(reg, covariance=reg.covariance + 0.5 * (C + C.T))


def instrument_for(setup: TotalStationSetup) -> Instrument:
    """The accuracy model of a project's total station setup."""
    return make_instrument(
        setup.instrument, setup.distance_sigma_mm, setup.distance_ppm, setup.angle_sigma_arcsec
    )


def localize_station(
    project: Project,
    T_world_base: np.ndarray,
    rng: np.random.Generator,
    station_id: str | None = None,
    built: Sequence[Element] = (),
) -> BasePose:
    """Simulate a total station localization of the robot base at one station.

    When the project's setup names measured ``observations`` and
    ``robot_points`` files, those are used instead (:func:`localize_files`)
    and ``T_world_base``, ``rng`` and ``built`` are not.

    The prism points are chosen in the base frame (eqs 9-11 for the
    ``arbitrary`` procedure, then moved clear of ``built`` and of the line of
    sight; ``P1, P1 + d x, P1 + d y`` for ``three_point``), reached by
    inverse kinematics and placed by forward kinematics of the project's robot.
    The true prism positions (plus the robot's repeatability noise) are
    observed from ``T_world_instrument`` with the instrument's noise, and the
    base pose is estimated from the readings.

    Parameters
    ----------
    project
        The project (``localization.total_station``, ``robot``, ``simulation``).
    T_world_base
        True 4x4 pose of the robot base in the world (metres).
    rng
        Source of all noise.
    station_id
        Stored in the result.
    built
        Elements already built (obstacles for the prism, the arm and the line of sight).

    Returns
    -------
    BasePose
        Estimated pose with covariance, residuals and quality figures.
    """
    setup = project.localization.total_station or TotalStationSetup()
    if setup.observations is not None and setup.robot_points is not None:
        # measured readings were supplied: localize from them, nothing is simulated
        return localize_files(
            setup.observations,
            setup.robot_points,
            project=project,
            robot_sigma=project.simulation.robot_repeatability,
            station=station_id,
        )
    instrument = instrument_for(setup)
    T_world_instrument = setup.T_world_instrument.matrix()
    T_world_instrument[:3, 3] += T_world_instrument[:3, 2] * setup.instrument_height
    T_world_base = np.asarray(T_world_base, dtype=float)
    T_base_world = inv_T(T_world_base)
    T_flange_tool = project.robot.tool.T_flange_tool.matrix()
    kin = _kinematics(project.robot.model, T_flange_tool, setup.z_min)
    ws = kin.workspace
    boxes = boxes_from_elements(built, T_world_base)
    rules = ClearanceRules(
        tool_half_extents=setup.tool_half_extents,
        sight_from=tuple(float(v) for v in apply_T(T_base_world, T_world_instrument[:3, 3])),
    )
    moved = np.zeros(0)
    dropped: tuple[tuple[int, str], ...] = ()
    if setup.procedure == "three_point":
        d = setup.three_point_step
        c = np.asarray(ws.center)
        p1 = c + np.array([0.55 * ws.radius - 0.5 * d, -0.5 * d, 0.0])
        P_des = three_point_base_points(p1, d)
        ok = clear_mask(P_des, ws, boxes, rules)
        if not ok.all():
            raise LocalizationError(
                f"station {station_id}: three-point localization point P{int(np.argmin(ok)) + 1} "
                "is blocked or out of reach; use procedure 'arbitrary'"
            )
    else:
        clear = avoid_obstacles(
            _cached_optimal_points(setup.n_points, ws), ws, boxes, rules, min_points=3
        )
        P_des, moved, dropped = clear.points, clear.moved, clear.dropped
    P_base = kin.prism_points(P_des)
    sigma_robot = project.simulation.robot_repeatability
    P_true = P_base + rng.normal(0.0, 1.0, P_base.shape) * sigma_robot
    # the instrument really stands where its (uncertain) set-up puts it, off by a draw
    C_setup = setup_covariance(setup)
    T_world_instrument_true = perturb(
        T_world_instrument, rng.normal(0.0, 1.0, 6) * np.sqrt(np.diag(C_setup))
    )
    p_instr = apply_T(inv_T(T_world_instrument_true), apply_T(T_world_base, P_true))
    hz, v, sd = simulate_polar(p_instr, instrument, rng)
    M, C = to_world(
        T_world_instrument, polar_to_cartesian(hz, v, sd), polar_covariance(hz, v, sd, instrument)
    )
    assert C is not None
    if setup.procedure == "three_point":
        reg = localize_three_point(M, P_base[0], setup.three_point_step, C, sigma_robot)
    else:
        reg = register_points(
            P_base, M, point_cov=C, base_sigma=sigma_robot, reject_outlier=len(P_base) >= 5
        )
    reg = add_instrument_uncertainty(reg, T_world_instrument, C_setup)
    quality = {
        "procedure": setup.procedure,
        "instrument": instrument.name,
        "points_base": P_base.tolist(),
        "points_world": M.tolist(),
        "slope_distances": sd.tolist(),
        "moved_for_obstacles": moved.tolist(),
        "dropped_points": [why for _, why in dropped],
    }
    return reg.to_base_pose(station=station_id, quality=quality)


def prism_points_from_joints(
    model: str,
    joints: np.ndarray,
    T_flange_prism: np.ndarray,
    source: str | None = None,
    lines: Sequence[int] = (),
) -> np.ndarray:
    """Prism positions ``(n, 3)`` in the base frame from joint values ``(n, dof)`` (radians).

    Raises
    ------
    InputError
        When the number of joints does not match the robot or a configuration
        lies outside the joint limits (the robot cannot have stood there).
    """
    from fabflow.robots import get_robot

    rob = get_robot(model)
    q = np.asarray(joints, dtype=float)
    if q.shape[1] != rob.dof:
        raise InputError(
            f"{model} has {rob.dof} joints but the file gives {q.shape[1]} (q1_deg..)", source
        )
    ok = rob.within_limits(q)
    if not ok.all():
        k = int(np.argmin(ok))
        where = f"line {lines[k]}" if lines else None
        raise InputError(f"joint values outside the limits of {model}", source, where)
    return (rob.fk(q) @ np.asarray(T_flange_prism, dtype=float))[:, :3, 3]


def _triple(text: str | None, name: str, default: tuple[float, float, float]) -> np.ndarray:
    if text is None:
        return np.asarray(default, dtype=float)
    try:
        values = [float(v) for v in text.replace(";", ",").split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(np.isfinite(values)):
        raise InputError(f"{name} must be three numbers 'a,b,c', got {text!r}")
    return np.asarray(values, dtype=float)


def localize_files(
    observations_path: str | Path,
    robot_points_path: str | Path,
    *,
    project: Project | None = None,
    instrument: str | None = None,
    distance_sigma_mm: float | None = None,
    distance_ppm: float | None = None,
    angle_sigma_arcsec: float | None = None,
    instrument_xyz: str | None = None,
    instrument_abc_deg: str | None = None,
    instrument_height: float | None = None,
    robot_sigma: float = 0.0,
    method: Literal["closed_form", "optimize"] = "closed_form",
    reject_outlier: bool = True,
    station: str | None = None,
    robot: str | None = None,
    tcp_xyz: str | None = None,
) -> BasePose:
    """Localize from an observation file and a robot point file (CLI ``localize total-station``).

    The instrument and its pose come from the project's
    ``localization.total_station`` section when ``project`` is given, else from
    the defaults (Leica MS50, instrument frame = world); the keyword arguments
    override either. Pose strings are ``"x,y,z"`` (metres) and ``"A,B,C"``
    (degrees, R = Rz(A) Ry(B) Rx(C)). A robot point file of joint values is
    turned into prism positions by forward kinematics of ``robot`` (else the
    project's robot) with the prism at the project's TCP, or at ``tcp_xyz``
    (metres, flange frame).
    """
    setup = TotalStationSetup()
    if project is not None and project.localization.total_station is not None:
        setup = project.localization.total_station
    T0 = setup.T_world_instrument if project is not None else None
    inst = make_instrument(
        instrument or setup.instrument,
        distance_sigma_mm if distance_sigma_mm is not None else setup.distance_sigma_mm,
        distance_ppm if distance_ppm is not None else setup.distance_ppm,
        angle_sigma_arcsec if angle_sigma_arcsec is not None else setup.angle_sigma_arcsec,
    )
    xyz = _triple(instrument_xyz, "--instrument-xyz", T0.xyz if T0 else (0.0, 0.0, 0.0))
    abc = _triple(instrument_abc_deg, "--instrument-abc-deg", T0.abc_deg if T0 else (0.0, 0.0, 0.0))
    T_world_instrument = make_T(matrix_from_abc(*np.radians(abc)), xyz)
    hi = setup.instrument_height if instrument_height is None else instrument_height
    T_world_instrument[:3, 3] += T_world_instrument[:3, 2] * hi
    obs = read_observations(observations_path)
    rp = read_robot_points(robot_points_path)
    if rp.xyz is not None:
        pts = rp.xyz
    else:
        assert rp.joints is not None
        model = robot or (project.robot.model if project is not None else None)
        if model is None:
            raise InputError(
                "the robot point file holds joint values; name the robot (--robot or --project)",
                rp.source,
            )
        T_flange_tool = (
            project.robot.tool.T_flange_tool.matrix() if project is not None else np.eye(4)
        )
        if tcp_xyz is not None:
            T_flange_tool = make_T(T_flange_tool[:3, :3], _triple(tcp_xyz, "--tcp-xyz", (0, 0, 0)))
        pts = prism_points_from_joints(model, rp.joints, T_flange_tool, rp.source, rp.lines)
    reg, matched = localize_observations(
        obs, rp.point_ids, pts, inst, T_world_instrument, robot_sigma, method, reject_outlier
    )
    if project is not None:
        reg = add_instrument_uncertainty(reg, T_world_instrument, setup_covariance(setup))
    quality = {
        "instrument": inst.name,
        "point_ids": list(matched),
        "observations": str(observations_path),
        "robot_points": str(robot_points_path),
        "T_world_instrument": T_world_instrument.tolist(),
    }
    return reg.to_base_pose(station=station, quality=quality)
