"""UWB multilateration: LS, WLS and WLS-T, and the Cramer-Rao bound.

Implements seeds/003 section 3.3.2 (equations 6-15), vectorized over epochs:

``ls``
    Linearized least squares (equations 7-10): the squared range equations are
    differenced against a reference anchor (the first one with a range in that
    epoch), which cancels the unknown ``|x|^2``; the linear system ``A x = b``
    is solved by ordinary least squares.
``wls``
    Weighted linear least squares (equations 11-12) with weights from the
    range-dependent variance. Instead of differencing (which correlates the rows
    through the shared reference) the nuisance ``R = |x|^2`` is kept as an
    unknown: rows ``[-2 a_i, 1] [x; R] = d_i^2 - |a_i|^2`` then have independent
    errors ``2 d_i e_i`` and the diagonal weight ``1 / (4 d_i^2 sigma_i^2)``;
    this is the best linear unbiased estimate the differenced form gives with
    its full covariance. With exactly ``dim + 1`` anchors it equals ``ls``.
``wls-t``
    ``wls`` followed by Gauss-Newton (Taylor, equations 13-15) iterations on the
    weighted range residuals ``d_i - |x - a_i|``, until the step is below
    ``tol`` or after ``max_iter`` iterations. This is the maximum-likelihood
    estimate for Gaussian range noise, the estimator that can reach the
    Cramer-Rao bound (:func:`crlb`).

Frames: anchors, ranges and positions share one frame (the UWB frame, or the
world after applying ``T_world_uwb``); metres throughout.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy import special

from fabflow.errors import InputError, LocalizationError

Method = Literal["ls", "wls", "wls-t"]
Sigma = float | Callable[[np.ndarray], np.ndarray]
"""Range noise standard deviation (metres): a constant or a function of the range."""

METHODS: tuple[str, ...] = ("ls", "wls", "wls-t")
UNOBSERVED_VARIANCE = 1.0
"""Variance (rad^2) reported for pose components the measurement does not observe."""
MIN_RANGE_FOR_WEIGHT = 0.1
"""Ranges below this (metres) are weighted as if this long (keeps the WLS weights finite)."""
COND_LIMIT = 1e10
"""Normal matrices worse conditioned than this count as singular (degenerate geometry)."""


@dataclass(frozen=True)
class UwbFix:
    """Per-epoch multilateration results.

    Attributes
    ----------
    positions
        (N, dim) estimated positions (metres); NaN where ``valid`` is False.
    covariances
        (N, dim, dim) position covariances (m^2) under the given noise model; NaN
        where ``valid`` is False.
    residuals
        (N, n_anchors) range residuals ``measured - |x - a_i|`` (metres), NaN for
        missing ranges and invalid epochs.
    valid
        (N,) epochs with a solution.
    too_few
        (N,) epochs with fewer than ``dim + 1`` ranges.
    degenerate
        (N,) epochs whose available anchors do not fix the position (ill-conditioned).
    iterations
        (N,) Gauss-Newton iterations (0 for ``ls``/``wls``).
    converged
        (N,) whether the iterations met the tolerance (True for ``ls``/``wls``).
    method
        The estimator used.
    excluded
        (N, n_anchors) ranges left out by the tests (with ``alpha``).
    test_failed
        (N,) epochs whose tests still fail after the exclusions (then invalid).
    """

    positions: np.ndarray
    covariances: np.ndarray
    residuals: np.ndarray
    valid: np.ndarray
    too_few: np.ndarray
    degenerate: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    method: str
    excluded: np.ndarray | None = None
    test_failed: np.ndarray | None = None


def sigma_of(sigma: Sigma, d: np.ndarray) -> np.ndarray:
    """Range standard deviations (metres) at distances ``d``: a constant, or a function of ``d``."""
    if callable(sigma):
        s = np.asarray(sigma(d), dtype=float)
    else:
        s = np.full(np.shape(d), float(sigma))
    return np.broadcast_to(s, np.shape(d))


def _check_inputs(anchors: Any, ranges: Any) -> tuple[np.ndarray, np.ndarray, bool]:
    A = np.asarray(anchors, dtype=float)
    if A.ndim != 2 or A.shape[1] not in (2, 3):
        raise InputError(f"anchors must be (n_anchors, 2) or (n_anchors, 3), got {A.shape}")
    dim = A.shape[1]
    if A.shape[0] < dim + 1:
        raise InputError(
            f"{dim}D multilateration needs at least {dim + 1} anchors, got {A.shape[0]}"
        )
    if not np.all(np.isfinite(A)):
        raise InputError("anchor coordinates must be finite")
    r = np.asarray(ranges, dtype=float)
    single = r.ndim == 1
    if single:
        r = r[None]
    if r.ndim != 2 or r.shape[1] != A.shape[0]:
        raise InputError(
            f"ranges must be (N, {A.shape[0]}) for {A.shape[0]} anchors, got {np.shape(ranges)}"
        )
    problem = anchor_geometry_problem(A)
    if problem is not None:
        raise LocalizationError(problem)
    return A, r, single


def anchor_geometry_problem(anchors: np.ndarray) -> str | None:
    """Why anchors ``(n, 2)`` or ``(n, 3)`` (metres) cannot fix a position, or ``None``.

    In 3D they must not be coplanar (nor collinear), in 2D not collinear.
    """
    A = np.asarray(anchors, dtype=float)
    dim = A.shape[1]
    sv = np.linalg.svd(A - A.mean(axis=0), compute_uv=False)
    if sv[dim - 1] >= 1e-6 * max(sv[0], 1e-12):
        return None
    shape = "collinear" if dim == 2 else "coplanar (or collinear)"
    return (
        f"degenerate anchor geometry: the {A.shape[0]} anchors are {shape}, so the "
        f"{dim}D position is not determined"
        + ("; use 2D positioning with a known height" if dim == 3 else "")
    )


def _inv_batched(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of symmetric positive (semi)definite (N, n, n) matrices and a conditioning measure.

    The measure ``det(M) / (trace(M) / n)^n`` is 1 for a multiple of the identity
    and tends to 0 as ``M`` becomes singular (it is at most ``n^n`` times the
    ratio of the smallest to the largest eigenvalue). 2x2 and 3x3 use closed
    forms, which are several times faster than LAPACK on many small matrices.
    """
    n = M.shape[-1]
    tr = np.trace(M, axis1=-2, axis2=-1) / n
    if n == 2:
        a, b, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 1]
        det = a * d - b * b
        adj = np.empty_like(M)
        adj[:, 0, 0], adj[:, 1, 1], adj[:, 0, 1], adj[:, 1, 0] = d, a, -b, -b
    elif n == 3:
        a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
        d, e, f = M[:, 1, 1], M[:, 1, 2], M[:, 2, 2]
        A0, B0, C0 = d * f - e * e, c * e - b * f, b * e - c * d
        det = a * A0 + b * B0 + c * C0
        adj = np.empty_like(M)
        adj[:, 0, 0], adj[:, 0, 1], adj[:, 0, 2] = A0, B0, C0
        adj[:, 1, 0], adj[:, 1, 1], adj[:, 1, 2] = B0, a * f - c * c, b * c - a * e
        adj[:, 2, 0], adj[:, 2, 1], adj[:, 2, 2] = C0, b * c - a * e, a * d - b * b
    else:
        det = np.linalg.det(M)
        with np.errstate(all="ignore"):
            good = np.abs(det) > 0
            safe = np.where(good[:, None, None], M, np.eye(n))
            inv = np.linalg.inv(safe)
            inv[~good] = np.nan
            return inv, det / tr**n
    with np.errstate(all="ignore"):
        return adj / det[:, None, None], det / tr**n


def _solve_batched(M: np.ndarray, rhs: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``M x = rhs`` where ``ok`` and M is well conditioned; (x, M^-1), NaN elsewhere."""
    Minv, cond = _inv_batched(M)
    good = ok & (cond > 1.0 / COND_LIMIT)
    x = np.einsum("nij,nj->ni", Minv, rhs)
    x[~good] = np.nan
    Minv[~good] = np.nan
    return x, Minv


def _ls(
    A: np.ndarray, r: np.ndarray, mask: np.ndarray, ok: np.ndarray, sigma: Sigma
) -> tuple[np.ndarray, np.ndarray]:
    N = r.shape[0]
    ref = np.argmax(mask, axis=1)
    rows = np.arange(N)
    a_ref = A[ref]
    d = np.where(mask, r, 0.0)
    d_ref = d[rows, ref]
    w = mask.copy()
    w[rows, ref] = False
    w = w.astype(float)
    sq = np.sum(A**2, axis=1)
    H = 2.0 * (A[None] - a_ref[:, None])
    b = (sq[None] - d**2) - (sq[ref] - d_ref**2)[:, None]
    M = np.einsum("nij,ni,nik->njk", H, w, H)
    rhs = np.einsum("nij,ni,ni->nj", H, w, b)
    x, Minv = _solve_batched(M, rhs, ok)
    # covariance of the differenced rows: 4 (diag(d_i^2 s_i^2) + d_ref^2 s_ref^2 11^T)
    s = sigma_of(sigma, np.maximum(d, MIN_RANGE_FOR_WEIGHT))
    var = (d * s) ** 2
    Hw = H * w[..., None]
    C_diag = np.einsum("nij,ni,nik->njk", Hw, var, Hw)
    Hsum = Hw.sum(axis=1)
    C = 4.0 * (C_diag + var[rows, ref][:, None, None] * Hsum[:, :, None] * Hsum[:, None, :])
    cov = Minv @ C @ Minv
    return x, cov


def _wls(
    A: np.ndarray, r: np.ndarray, mask: np.ndarray, ok: np.ndarray, sigma: Sigma
) -> tuple[np.ndarray, np.ndarray]:
    n = r.shape[1]
    dim = A.shape[1]
    d = np.where(mask, r, 0.0)
    dw = np.maximum(d, MIN_RANGE_FOR_WEIGHT)
    s = sigma_of(sigma, dw)
    w = np.where(mask, 1.0 / (4.0 * dw**2 * s**2), 0.0)
    # about the anchors' centre: the same solution (the model is an affine change of
    # its unknowns away), but far from the origin the column of ones would be
    # outscaled and the normal matrix taken as singular
    centre = A.mean(axis=0)
    Ac = A - centre
    H = np.concatenate([-2.0 * Ac, np.ones((n, 1))], axis=1)
    b = d**2 - np.sum(Ac**2, axis=1)[None]
    M = np.einsum("ij,ni,ik->njk", H, w, H)
    rhs = np.einsum("ij,ni,ni->nj", H, w, b)
    theta, Minv = _solve_batched(M, rhs, ok)
    return theta[:, :dim] + centre, Minv[:, :dim, :dim]


LINE_SEARCH = 0.5 ** np.arange(8)
"""Step fractions tried by the damped Gauss-Newton, largest first."""


def _gauss_newton(
    A: np.ndarray,
    r: np.ndarray,
    mask: np.ndarray,
    x0: np.ndarray,
    sigma: Sigma,
    max_iter: int,
    tol: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Damped Newton / Gauss-Newton on the weighted range residuals, batched over epochs.

    Each step is scaled by the largest of :data:`LINE_SEARCH` that
    lowers the cost, so a fix never ends at a worse cost than its start (an
    undamped step can overshoot on a flat, near-coplanar geometry). An epoch has
    converged when a step is below ``tol`` or negligible against its own
    uncertainty (``step^T N step < 1e-6``: a thousandth of its sigma); one that has
    not after ``max_iter`` iterations, or finds no step that lowers the cost
    before converging, is reported as not converged (and :func:`locate` marks it
    invalid).
    """
    d = np.where(mask, r, 0.0)
    s = sigma_of(sigma, np.maximum(d, MIN_RANGE_FOR_WEIGHT))
    w = np.where(mask, 1.0 / s**2, 0.0)
    x = x0.copy()
    dim = x.shape[1]
    ok = np.all(np.isfinite(x), axis=1)
    active = ok.copy()
    iterations = np.zeros(len(x), dtype=int)
    converged = np.zeros(len(x), dtype=bool)
    cov = np.full((len(x), dim, dim), np.nan)

    def cost_of(xs: np.ndarray, rows: np.ndarray) -> np.ndarray:
        diff = xs[..., None, :] - A
        res = d[rows] - np.sqrt(np.einsum("...ij,...ij->...i", diff, diff))
        return np.einsum("...i,...i->...", w[rows] * res, res)

    for _ in range(max_iter):
        if not active.any():
            break
        idx = np.flatnonzero(active)
        xa = x[idx]
        diff = xa[:, None, :] - A[None]
        dist = np.maximum(np.sqrt(np.einsum("nij,nij->ni", diff, diff)), 1e-9)
        J = diff / dist[..., None]
        res = d[idx] - dist
        cost = np.einsum("ni,ni->n", w[idx] * res, res)
        Jw = J * w[idx][..., None]
        M = np.matmul(Jw.transpose(0, 2, 1), J)
        g = np.einsum("nij,ni->nj", Jw, res)
        # Newton's Hessian adds the curvature of the ranges, which Gauss-Newton
        # drops; it converges in a few steps where the residuals are not small
        # against the curvature (a flat, near-coplanar geometry). Where it is not
        # positive definite the Gauss-Newton matrix is used.
        curv = np.einsum("ni,nij,nik->njk", w[idx] * res / dist, J, J)
        H = M - (np.einsum("ni->n", w[idx] * res / dist)[:, None, None] * np.eye(dim) - curv)
        H_ok = np.all(np.linalg.eigvalsh(H) > 1e-9 * np.trace(M, axis1=1, axis2=2)[:, None], 1)
        step, _ = _solve_batched(np.where(H_ok[:, None, None], H, M), g, np.ones(idx.size, bool))
        _, Minv = _solve_batched(M, g, np.ones(idx.size, dtype=bool))
        bad = ~np.all(np.isfinite(step), axis=1)
        step[bad] = 0.0
        cov[idx] = Minv
        iterations[idx] += 1
        tiny = (np.einsum("ni,nij,nj->n", step, M, step) < 1e-6) | (
            np.einsum("ni,ni->n", step, step) < tol * tol
        )
        trials = xa[None] + LINE_SEARCH[:, None, None] * step[None]
        lower = cost_of(trials, idx[None].repeat(len(LINE_SEARCH), 0)) <= cost[None]
        best = np.argmax(lower, axis=0)
        found = lower[best, np.arange(idx.size)]
        move = found & ~tiny & ~bad
        x[idx[move]] = trials[best[move], np.flatnonzero(move)]
        converged[idx] = tiny & ~bad
        ok[idx[bad]] = False
        active[idx[tiny | bad | ~found]] = False
    ok &= np.all(np.isfinite(cov), axis=(1, 2))
    return x, cov, ok, iterations, converged


def locate(
    anchors: np.ndarray,
    ranges: np.ndarray,
    method: Method = "wls-t",
    sigma: Sigma = 0.05,
    max_iter: int = 50,
    tol: float = 1e-5,
    alpha: float | None = None,
) -> UwbFix:
    """Multilaterate tag positions from anchor ranges, one fix per epoch.

    Parameters
    ----------
    anchors
        (n_anchors, dim) anchor positions, dim 2 or 3 (metres). In 2D the ranges
        must be horizontal (see :func:`horizontal_ranges`).
    ranges
        (N, n_anchors) measured (calibrated) ranges in metres, NaN where missing;
        a single epoch may be given as (n_anchors,).
    method
        ``"ls"``, ``"wls"`` or ``"wls-t"`` (see the module docstring).
    sigma
        Range noise standard deviation (metres), a constant or a function of the
        range; used for the weights and the reported covariances.
    max_iter, tol
        Iteration cap and step tolerance (metres) of the damped Gauss-Newton
        (Levenberg-Marquardt) refinement of ``wls-t``; an epoch that has not
        converged within ``max_iter`` is invalid.
    alpha
        With ``wls-t``: test every fix (global test and a w-test per range, at
        level ``alpha``, Bonferroni over the ranges) and leave out the worst range
        while the tests fail and two degrees of freedom remain (Baarda's data
        snooping: one faulty range, e.g. a non-line-of-sight delay, is found and
        excluded). Fixes that still fail are invalid. ``None``: no tests.

    Returns
    -------
    UwbFix
        Positions, covariances, residuals and per-epoch validity. Epochs with fewer
        than ``dim + 1`` ranges or an ill-conditioned geometry are marked invalid
        (NaN) rather than raising, so one bad epoch does not void a batch.

    Raises
    ------
    InputError
        For malformed arrays or an unknown method.
    LocalizationError
        When the anchors themselves cannot determine a position (collinear in 2D,
        coplanar in 3D).
    """
    if method not in METHODS:
        raise InputError(f"unknown UWB method {method!r}; expected one of {', '.join(METHODS)}")
    A, r, _ = _check_inputs(anchors, ranges)
    dim = A.shape[1]
    mask = np.isfinite(r) & (r >= 0)
    count = mask.sum(axis=1)
    too_few = count < dim + 1
    ok = ~too_few
    if method == "ls":
        x, cov = _ls(A, r, mask, ok, sigma)
        iterations = np.zeros(len(r), dtype=int)
        converged = np.ones(len(r), dtype=bool)
    else:
        x, cov = _wls(A, r, mask, ok, sigma)
        iterations = np.zeros(len(r), dtype=int)
        converged = np.ones(len(r), dtype=bool)
        if method == "wls-t":
            x, cov, _, iterations, converged = _gauss_newton(A, r, mask, x, sigma, max_iter, tol)
    excluded = test_failed = None
    if alpha is not None and method == "wls-t":
        x, cov, converged, mask, excluded, test_failed = _snoop(
            A, r, mask, x, cov, converged, sigma, alpha, max_iter, tol
        )
        converged = converged & ~test_failed
    valid = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(cov), axis=(1, 2)) & converged
    x[~valid] = np.nan
    cov[~valid] = np.nan
    dist = np.linalg.norm(x[:, None, :] - A[None], axis=-1)
    residuals = np.where(mask & valid[:, None], r - dist, np.nan)
    return UwbFix(
        positions=x,
        covariances=cov,
        residuals=residuals,
        valid=valid,
        too_few=too_few,
        degenerate=ok & ~valid,
        iterations=iterations,
        converged=converged & valid,
        method=method,
        excluded=excluded,
        test_failed=test_failed,
    )


def range_tests(
    A: np.ndarray, r: np.ndarray, mask: np.ndarray, x: np.ndarray, sigma: Sigma, alpha: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Global test and w-test of every range of every fix, batched over epochs.

    Parameters
    ----------
    A
        (n, dim) anchors; ``r`` (N, n) ranges; ``mask`` (N, n) the ranges used;
        ``x`` (N, dim) the fixes (metres).
    sigma
        Range noise standard deviation (constant or function of the range).
    alpha
        Level of the global test; the w-tests share it over the ranges of a fix.

    Returns
    -------
    w
        (N, n) ``|w|`` of each used range (NaN elsewhere), standard normal without a fault.
    w_threshold
        (N,) critical ``|w|`` of each fix.
    failed
        (N,) fixes whose global test or a w-test fails.
    redundancy
        (N,) degrees of freedom of each fix.
    """
    dim = A.shape[1]
    d = np.where(mask, r, 0.0)
    s = sigma_of(sigma, np.maximum(d, MIN_RANGE_FOR_WEIGHT))
    wgt = np.where(mask, 1.0 / s**2, 0.0)
    diff = x[:, None, :] - A[None]
    dist = np.maximum(np.linalg.norm(diff, axis=-1), 1e-9)
    J = diff / dist[..., None]
    v = np.where(mask, d - dist, 0.0)
    Ninv, _ = _inv_batched(np.einsum("ni,nij,nik->njk", wgt, J, J))
    q_vv = np.where(mask, s**2 - np.einsum("nij,njk,nik->ni", J, Ninv, J), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.abs(v) / np.sqrt(np.where(q_vv > 1e-12 * s**2, q_vv, np.nan))
    count = mask.sum(axis=1)
    redundancy = count - dim
    statistic = np.einsum("ni,ni->n", wgt * v, v)
    ok_r = redundancy > 0
    threshold_T = np.full(len(x), np.inf)
    threshold_T[ok_r] = special.chdtri(redundancy[ok_r], alpha)
    w_threshold = np.sqrt(special.chdtri(1, alpha / np.maximum(count, 1)))
    w_max = np.nanmax(np.where(mask, w, -np.inf), axis=1)
    failed = ok_r & ((statistic > threshold_T) | (w_max > w_threshold))
    return np.where(mask, w, np.nan), w_threshold, failed, redundancy


def _snoop(
    A: np.ndarray,
    r: np.ndarray,
    mask: np.ndarray,
    x: np.ndarray,
    cov: np.ndarray,
    converged: np.ndarray,
    sigma: Sigma,
    alpha: float,
    max_iter: int,
    tol: float,
) -> tuple[np.ndarray, ...]:
    """Iterative data snooping of every fix: leave out the worst range while tests fail."""
    mask = mask.copy()
    excluded = np.zeros_like(mask)
    x, cov, converged = x.copy(), cov.copy(), converged.copy()
    fixable = np.all(np.isfinite(x), axis=1)
    while True:
        w, _, failed, redundancy = range_tests(
            A, r, mask, np.where(fixable[:, None], x, 0), sigma, alpha
        )
        failed &= fixable
        again = failed & (redundancy >= 2) & np.any(np.isfinite(w), axis=1)
        if not again.any():
            return x, cov, converged, mask, excluded, failed
        rows = np.flatnonzero(again)
        worst = np.nanargmax(w[rows], axis=1)
        mask[rows, worst] = False
        excluded[rows, worst] = True
        xr, covr, _, _, conv = _gauss_newton(A, r[rows], mask[rows], x[rows], sigma, max_iter, tol)
        x[rows], cov[rows], converged[rows] = xr, covr, conv
        fixable[rows] &= np.all(np.isfinite(xr), axis=1)


def crlb(anchors: np.ndarray, position: np.ndarray, sigma: Sigma) -> np.ndarray:
    """Cramer-Rao lower bound on the position error covariance.

    For independent Gaussian range errors of standard deviation ``sigma_i`` (taken
    as known, evaluated at the true distance), the Fisher information is
    ``sum_i u_i u_i^T / sigma_i^2`` with ``u_i`` the unit vector from anchor ``i``
    to the position; its inverse bounds the covariance of any unbiased estimator.

    Parameters
    ----------
    anchors
        (n_anchors, dim) anchor positions (metres).
    position
        (dim,) or (N, dim) true positions (metres).
    sigma
        Range noise standard deviation (metres): constant or a function of distance.

    Returns
    -------
    np.ndarray
        (dim, dim) or (N, dim, dim) bound (m^2); ``sqrt(trace)`` is the smallest
        achievable RMS position error.

    Raises
    ------
    LocalizationError
        If the geometry leaves the position undetermined (singular information).
    """
    A = np.asarray(anchors, dtype=float)
    p = np.asarray(position, dtype=float)
    single = p.ndim == 1
    P = np.atleast_2d(p)
    if P.shape[1] != A.shape[1]:
        raise InputError(f"position has dimension {P.shape[1]}, anchors {A.shape[1]}")
    diff = P[:, None, :] - A[None]
    dist = np.linalg.norm(diff, axis=-1)
    u = diff / np.maximum(dist, 1e-12)[..., None]
    s = sigma_of(sigma, dist)
    F = np.einsum("nij,ni,nik->njk", u, 1.0 / s**2, u)
    ev = np.linalg.eigvalsh(F)
    if np.any(ev[:, 0] <= ev[:, -1] / COND_LIMIT):
        raise LocalizationError(
            "the anchor geometry does not determine the position (singular Fisher information)"
        )
    C = np.linalg.inv(F)
    return C[0] if single else C


def horizontal_ranges(ranges: np.ndarray, anchor_z: np.ndarray, tag_z: float) -> np.ndarray:
    """Project slant ranges to the horizontal plane for 2D positioning at a known height.

    ``sqrt(max(d^2 - (z_anchor - z_tag)^2, 0))``, anchors along the last axis.
    """
    r = np.asarray(ranges, dtype=float)
    dz = np.asarray(anchor_z, dtype=float) - tag_z
    return np.sqrt(np.maximum(r**2 - dz**2, 0.0))
