"""UWB multilateration: LS, WLS and WLS-T, the Cramer-Rao bound, and the platform pose.

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

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.result import BasePose

if TYPE_CHECKING:
    from fabflow.design.elements import Element
    from fabflow.project import Project, UwbSetup

Method = Literal["ls", "wls", "wls-t"]
Sigma = float | Callable[[np.ndarray], np.ndarray]
"""Range noise standard deviation (metres): a constant or a function of the range."""

METHODS: tuple[str, ...] = ("ls", "wls", "wls-t")
UNOBSERVED_VARIANCE = 1.0
"""Variance (rad^2) reported for pose components the measurement does not observe."""
_MIN_RANGE_FOR_WEIGHT = 0.1
_COND_LIMIT = 1e10


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


def _sigma_of(sigma: Sigma, d: np.ndarray) -> np.ndarray:
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
    spread = A - A.mean(axis=0)
    sv = np.linalg.svd(spread, compute_uv=False)
    if sv[dim - 1] < 1e-6 * max(sv[0], 1e-12):
        shape = "collinear" if dim == 2 else "coplanar (or collinear)"
        raise LocalizationError(
            f"degenerate anchor geometry: the {A.shape[0]} anchors are {shape}, so the "
            f"{dim}D position is not determined"
            + ("; use 2D positioning with a known height" if dim == 3 else "")
        )
    return A, r, single


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
    good = ok & (cond > 1.0 / _COND_LIMIT)
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
    s = _sigma_of(sigma, np.maximum(d, _MIN_RANGE_FOR_WEIGHT))
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
    dw = np.maximum(d, _MIN_RANGE_FOR_WEIGHT)
    s = _sigma_of(sigma, dw)
    w = np.where(mask, 1.0 / (4.0 * dw**2 * s**2), 0.0)
    H = np.concatenate([-2.0 * A, np.ones((n, 1))], axis=1)
    b = d**2 - np.sum(A**2, axis=1)[None]
    M = np.einsum("ij,ni,ik->njk", H, w, H)
    rhs = np.einsum("ij,ni,ni->nj", H, w, b)
    theta, Minv = _solve_batched(M, rhs, ok)
    return theta[:, :dim], Minv[:, :dim, :dim]


def _gauss_newton(
    A: np.ndarray,
    r: np.ndarray,
    mask: np.ndarray,
    x0: np.ndarray,
    sigma: Sigma,
    max_iter: int,
    tol: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    d = np.where(mask, r, 0.0)
    s = _sigma_of(sigma, np.maximum(d, _MIN_RANGE_FOR_WEIGHT))
    w = np.where(mask, 1.0 / s**2, 0.0)
    x = x0.copy()
    dim = x.shape[1]
    ok = np.all(np.isfinite(x), axis=1)
    active = ok.copy()
    iterations = np.zeros(len(x), dtype=int)
    converged = ~ok
    # the covariance is (J^T W J)^-1 of the last iteration: its step was below tol, so
    # the Jacobian is that of the solution to well within the noise
    cov = np.full((len(x), dim, dim), np.nan)
    for _ in range(max_iter):
        if not active.any():
            break
        idx = np.flatnonzero(active)
        all_active = idx.size == len(x)
        xa = x if all_active else x[idx]
        diff = xa[:, None, :] - A[None]
        dist = np.maximum(np.sqrt(np.einsum("nij,nij->ni", diff, diff)), 1e-9)
        J = diff / dist[..., None]
        res = (d if all_active else d[idx]) - dist
        wi = w if all_active else w[idx]
        Jw = J * wi[..., None]
        M = np.matmul(Jw.transpose(0, 2, 1), J)
        g = np.einsum("nij,ni->nj", Jw, res)
        step, Minv = _solve_batched(M, g, np.ones(idx.size, dtype=bool))
        bad = ~np.all(np.isfinite(step), axis=1)
        step[bad] = 0.0
        x[idx] = xa + step
        cov[idx] = Minv
        iterations[idx] += 1
        done = np.einsum("ni,ni->n", step, step) < tol * tol
        converged[idx] = done & ~bad
        ok[idx[bad]] = False
        active[idx[done | bad]] = False
    ok &= np.all(np.isfinite(cov), axis=(1, 2))
    return x, cov, ok, iterations, converged


def locate(
    anchors: np.ndarray,
    ranges: np.ndarray,
    method: Method = "wls-t",
    sigma: Sigma = 0.05,
    max_iter: int = 10,
    tol: float = 1e-5,
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
        Gauss-Newton iteration cap and step tolerance (metres) for ``wls-t``.

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
    valid = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
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
    )


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
    s = _sigma_of(sigma, dist)
    F = np.einsum("nij,ni,nik->njk", u, 1.0 / s**2, u)
    ev = np.linalg.eigvalsh(F)
    if np.any(ev[:, 0] <= ev[:, -1] / _COND_LIMIT):
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


# ------------------------------------------------------------------ platform pose


def _rotz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class PlatformFix:
    """A static platform pose (level platform) from the ranges of one or more tags.

    Attributes
    ----------
    state
        ``[x, y, z, yaw]`` of the platform frame in the anchors' frame (metres, rad).
    covariance
        4x4 covariance of ``state`` (yaw variance is ``UNOBSERVED_VARIANCE`` when no
        tag pair or prior fixes it).
    residuals
        (n_used,) range residuals of the measurements used (metres).
    n_ranges, n_used
        Ranges given (finite) and used after the residual test.
    iterations
        Gauss-Newton iterations of the final solve.
    heading_observed
        Whether the yaw is determined by the measurements (or a prior).
    per_anchor_rms
        (n_anchors,) RMS residual of the used ranges per anchor (metres).
    """

    state: np.ndarray
    covariance: np.ndarray
    residuals: np.ndarray
    n_ranges: int
    n_used: int
    iterations: int
    heading_observed: bool
    per_anchor_rms: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def T(self) -> np.ndarray:
        """4x4 platform pose (``T_frame_platform``)."""
        T = np.eye(4)
        T[:3, :3] = _rotz(float(self.state[3]))
        T[:3, 3] = self.state[:3]
        return T


def locate_platform(
    anchors: np.ndarray,
    ranges: np.ndarray,
    lever_arms: np.ndarray,
    sigma: Sigma,
    method: Method = "wls-t",
    heading_prior: tuple[float, float] | None = None,
    outlier_k: float = 4.0,
    max_iter: int = 20,
    anchor_bias_sigma: np.ndarray | None = None,
) -> PlatformFix:
    """Estimate a standing platform's ``x, y, z, yaw`` from the ranges of its tags.

    Every tag's epochs are first multilaterated with ``method``; the median tag
    positions give the initial pose (2D Procrustes fit of the lever arms). For
    ``wls-t`` the pose is then refined by Gauss-Newton on all ranges of all tags
    and epochs jointly, ranges with ``|residual| > outlier_k * sigma`` are dropped
    once and the solve repeated. Roll and pitch are taken as zero (a level
    platform); they are not observed.

    Parameters
    ----------
    anchors
        (n_anchors, 3) anchor positions (metres).
    ranges
        (N, n_tags, n_anchors) calibrated ranges (metres), NaN where missing.
    lever_arms
        (n_tags, 3) tag positions in the platform frame (metres).
    sigma
        Range noise standard deviation (constant or function of range).
    method
        Estimator for the per-epoch tag fixes; ``wls-t`` also refines jointly.
    heading_prior
        ``(yaw, sigma_yaw)`` in radians; required with a single tag, optional otherwise.
    outlier_k
        Residual test threshold in standard deviations.
    max_iter
        Gauss-Newton iteration cap.
    anchor_bias_sigma
        (n_anchors,) standard deviation (metres) of a range error shared by every
        range to an anchor (what the calibration leaves); added to the covariance,
        since averaging over epochs does not reduce it.

    Raises
    ------
    LocalizationError
        Too few valid fixes, or a single tag without a heading prior.
    """
    A = np.asarray(anchors, dtype=float)
    R = np.asarray(ranges, dtype=float)
    L = np.asarray(lever_arms, dtype=float)
    if A.ndim != 2 or A.shape[1] != 3:
        raise InputError(f"platform localization needs 3D anchors, got {A.shape}")
    if R.ndim != 3 or R.shape[1:] != (L.shape[0], A.shape[0]):
        raise InputError(
            f"ranges must be (N, {L.shape[0]} tags, {A.shape[0]} anchors), got {R.shape}"
        )
    n_tags = L.shape[0]
    if n_tags == 1 and heading_prior is None:
        raise LocalizationError(
            "one UWB tag cannot observe the heading of a standing platform; add a second "
            "tag or give a heading prior (from the motion or the IMU)"
        )
    tag_pos = np.empty((n_tags, 3))
    for k in range(n_tags):
        fix = locate(A, R[:, k, :], method=method, sigma=sigma)
        if not fix.valid.any():
            raise LocalizationError(
                f"tag {k}: no epoch has enough usable ranges ({int((~fix.too_few).sum())} of "
                f"{len(fix.valid)} epochs with >= 4 ranges, {int(fix.degenerate.sum())} degenerate)"
            )
        tag_pos[k] = np.nanmedian(fix.positions[fix.valid], axis=0)
    if n_tags >= 2:
        lc = L[:, :2] - L[:, :2].mean(axis=0)
        mc = tag_pos[:, :2] - tag_pos[:, :2].mean(axis=0)
        yaw0 = np.arctan2(np.sum(lc[:, 0] * mc[:, 1] - lc[:, 1] * mc[:, 0]), np.sum(lc * mc))
        spread = np.linalg.norm(lc, axis=1).max()
        heading_observed = spread > 0.05
    else:
        yaw0 = float(heading_prior[0])  # type: ignore[index]
        heading_observed = False
    if heading_prior is not None:
        heading_observed = True
        if n_tags >= 2 and not np.isfinite(yaw0):
            yaw0 = heading_prior[0]
    p0 = tag_pos.mean(axis=0) - _rotz(yaw0) @ L.mean(axis=0)
    state = np.array([*p0, yaw0])

    finite = np.isfinite(R)
    tag_idx = np.broadcast_to(np.arange(n_tags)[None, :, None], R.shape)[finite]
    anc_idx = np.broadcast_to(np.arange(A.shape[0])[None, None, :], R.shape)[finite]
    d = R[finite]
    s = _sigma_of(sigma, np.maximum(d, _MIN_RANGE_FOR_WEIGHT))
    use = np.ones(d.size, dtype=bool)
    iterations = 0
    if method == "wls-t" or not heading_observed or n_tags == 1:
        for _pass in range(2):
            state, iterations = _platform_gn(
                A, L, d[use], s[use], tag_idx[use], anc_idx[use], state, heading_prior, max_iter
            )
            res = d - _platform_h(A, L, state, tag_idx, anc_idx)
            keep = np.abs(res) <= outlier_k * s
            if np.array_equal(keep, use):
                break
            use = keep
    info = _platform_info(A, L, s[use], tag_idx[use], anc_idx[use], state, heading_prior)
    yaw_fixed = heading_observed
    if not yaw_fixed:
        info[3, :] = 0.0
        info[:, 3] = 0.0
        info[3, 3] = 1.0 / UNOBSERVED_VARIANCE
    ev = np.linalg.eigvalsh(info)
    if ev[0] <= ev[-1] / _COND_LIMIT:
        raise LocalizationError("the tag and anchor geometry does not determine the platform pose")
    cov = np.linalg.inv(info)
    if anchor_bias_sigma is not None:
        J = _platform_jac(A, L, state, tag_idx[use], anc_idx[use])
        if not yaw_fixed:
            J[:, 3] = 0.0
        G = cov @ (J / s[use][:, None] ** 2).T
        for j, sb in enumerate(np.asarray(anchor_bias_sigma, dtype=float)):
            g = G[:, anc_idx[use] == j].sum(axis=1)
            cov = cov + sb**2 * np.outer(g, g)
    res = d - _platform_h(A, L, state, tag_idx, anc_idx)
    per_anchor = np.array(
        [
            np.sqrt(np.mean(res[use & (anc_idx == j)] ** 2))
            if np.any(use & (anc_idx == j))
            else np.nan
            for j in range(A.shape[0])
        ]
    )
    state[3] = (state[3] + np.pi) % (2 * np.pi) - np.pi
    return PlatformFix(
        state=state,
        covariance=cov,
        residuals=res[use],
        n_ranges=int(d.size),
        n_used=int(use.sum()),
        iterations=iterations,
        heading_observed=yaw_fixed,
        per_anchor_rms=per_anchor,
    )


def _platform_h(
    A: np.ndarray, L: np.ndarray, state: np.ndarray, tag_idx: np.ndarray, anc_idx: np.ndarray
) -> np.ndarray:
    tags = state[:3] + L @ _rotz(state[3]).T
    return np.linalg.norm(tags[tag_idx] - A[anc_idx], axis=1)


def _platform_jac(
    A: np.ndarray, L: np.ndarray, state: np.ndarray, tag_idx: np.ndarray, anc_idx: np.ndarray
) -> np.ndarray:
    Rl = L @ _rotz(state[3]).T
    tags = state[:3] + Rl
    diff = tags[tag_idx] - A[anc_idx]
    u = diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-9)[:, None]
    dyaw = np.column_stack([-Rl[:, 1], Rl[:, 0]])[tag_idx]
    return np.column_stack([u, np.sum(u[:, :2] * dyaw, axis=1)])


def _platform_info(
    A: np.ndarray,
    L: np.ndarray,
    s: np.ndarray,
    tag_idx: np.ndarray,
    anc_idx: np.ndarray,
    state: np.ndarray,
    heading_prior: tuple[float, float] | None,
) -> np.ndarray:
    J = _platform_jac(A, L, state, tag_idx, anc_idx)
    info = J.T @ (J / s[:, None] ** 2)
    if heading_prior is not None:
        info[3, 3] += 1.0 / heading_prior[1] ** 2
    return info


def _platform_gn(
    A: np.ndarray,
    L: np.ndarray,
    d: np.ndarray,
    s: np.ndarray,
    tag_idx: np.ndarray,
    anc_idx: np.ndarray,
    state: np.ndarray,
    heading_prior: tuple[float, float] | None,
    max_iter: int,
) -> tuple[np.ndarray, int]:
    state = state.copy()
    iterations = 0
    while iterations < max_iter:
        iterations += 1
        J = _platform_jac(A, L, state, tag_idx, anc_idx)
        r = d - _platform_h(A, L, state, tag_idx, anc_idx)
        Wj = J / s[:, None] ** 2
        M = J.T @ Wj
        g = Wj.T @ r
        if heading_prior is not None:
            w = 1.0 / heading_prior[1] ** 2
            M[3, 3] += w
            g[3] += w * (np.angle(np.exp(1j * (heading_prior[0] - state[3]))))
        try:
            step = np.linalg.solve(M, g)
        except np.linalg.LinAlgError:
            raise LocalizationError(
                "the tag and anchor geometry does not determine the platform pose"
            ) from None
        state += step
        if np.linalg.norm(step) < 1e-8:
            break
    return state, iterations


def platform_to_base_covariance(
    T_world_platform: np.ndarray, T_platform_base: np.ndarray, cov_state: np.ndarray
) -> np.ndarray:
    """Map the 4x4 ``[x, y, z, yaw]`` covariance to the 6x6 base pose covariance.

    Follows the convention of :mod:`fabflow.positioning.result`: the yaw error is a
    rotation about the world z axis and moves the base origin by
    ``e_z x (t_base - t_platform)``. Roll and pitch get ``UNOBSERVED_VARIANCE``.
    """
    lever = T_world_platform[:3, :3] @ T_platform_base[:3, 3]
    J = np.zeros((6, 4))
    J[:3, :3] = np.eye(3)
    J[:3, 3] = np.cross([0.0, 0.0, 1.0], lever)
    J[5, 3] = 1.0
    cov = J @ cov_state @ J.T
    cov[3, 3] += UNOBSERVED_VARIANCE
    cov[4, 4] += UNOBSERVED_VARIANCE
    return 0.5 * (cov + cov.T)


# ------------------------------------------------------------- build pipeline


def _transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def anchors_world(setup: UwbSetup) -> tuple[list[str], np.ndarray]:
    """Anchor ids and their (n, 3) positions in the world (``T_world_uwb`` applied)."""
    ids = list(setup.anchors)
    A = np.array([setup.anchors[k] for k in ids], dtype=float)
    return ids, _transform_points(setup.T_world_uwb.matrix(), A)


def localize_station(
    project: Project,
    T_world_base: np.ndarray,
    rng: np.random.Generator,
    station_id: str | None = None,
    built: Sequence[Element] = (),
    heading_prior: tuple[float, float] | None = None,
) -> BasePose:
    """Simulate UWB localization of a parked platform and return the estimated base pose.

    The platform stands still for ``uwb.dwell_s`` seconds at the true pose; its
    tags (``uwb.tags``, platform frame) range to every anchor at ``uwb.rate_hz``
    with the simulator's error model (:class:`fabflow.sensors.uwb.UwbErrorModel` with
    ``sigma_1m = uwb.sigma``): distance-dependent noise, a per-anchor linear bias
    (fitted by a simulated calibration campaign and corrected), 2 % NLOS outliers,
    and NLOS with probability 0.5 on lines of sight blocked by ``built`` blocks.
    Outliers are rejected around each link's robust centre
    (:func:`~fabflow.positioning.uwb_calibration.reject_outliers_static`), then
    :func:`locate_platform` gives ``x, y, z, yaw``.

    Parameters
    ----------
    project
        The project (``localization.uwb`` and ``robot.platform.T_platform_base``).
    T_world_base
        4x4 true arm base pose (lift included); ``T_world_platform =
        T_world_base @ inv(T_platform_base)``.
    rng
        Random generator (all noise).
    station_id
        Stored in the result.
    built
        Elements already built; blocks occlude lines of sight.
    heading_prior
        ``(yaw, sigma)`` of the platform heading (radians); needed with one tag.

    Returns
    -------
    BasePose
        ``T_world_base`` estimate with a 6x6 covariance; roll and pitch are not
        observed (level platform assumed) and carry ``UNOBSERVED_VARIANCE``, as
        ``quality["unobserved"]`` says.
    """
    from fabflow.positioning.uwb_calibration import RangeCalibration, reject_outliers_static
    from fabflow.sensors.uwb import (
        UwbErrorModel,
        calibration_campaign,
        draw_bias,
        segments_occluded,
        simulate_ranges,
    )

    setup = project.localization.uwb
    if setup is None:
        raise InputError("the project has no 'localization.uwb' section", location="localization")
    ids, A = anchors_world(setup)
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    T_world_platform = np.asarray(T_world_base, dtype=float) @ np.linalg.inv(T_platform_base)
    L = np.asarray(setup.tags, dtype=float)
    tags_world = _transform_points(T_world_platform, L)

    model = UwbErrorModel(sigma_1m=setup.sigma)
    bias = draw_bias(len(ids), model, rng)
    cal = RangeCalibration.fit(*calibration_campaign(model, bias, rng))

    blocks = [e for e in built if e.extents is not None]
    occluded = None
    if blocks:
        T_boxes = np.stack([e.T_world_element for e in blocks])
        ext = np.stack([np.asarray(e.extents, dtype=float) for e in blocks])
        starts = np.repeat(tags_world, len(ids), axis=0)
        ends = np.tile(A, (len(L), 1))
        occluded = segments_occluded(starts, ends, T_boxes, ext).reshape(len(L), len(ids))

    n_rounds = max(1, round(setup.dwell_s * setup.rate_hz))
    tags_t = np.broadcast_to(tags_world, (n_rounds, *tags_world.shape))
    sim = simulate_ranges(
        A,
        tags_t,
        model,
        rng,
        bias=bias,
        occluded=None
        if occluded is None
        else np.broadcast_to(occluded, (n_rounds, *occluded.shape)),
    )
    ranges = cal.apply(sim.ranges)
    rej = reject_outliers_static(ranges, model.sigma(ranges))
    method: Method = "wls-t" if setup.estimator in ("wls-t", "eskf") else setup.estimator
    dist = np.linalg.norm(tags_world.mean(axis=0) - A, axis=1)
    fix = locate_platform(
        A,
        rej.ranges,
        L,
        model.sigma,
        method=method,
        heading_prior=heading_prior,
        anchor_bias_sigma=cal.bias_sigma(dist),
    )
    T_world_platform_est = fix.T
    T_world_base_est = T_world_platform_est @ T_platform_base
    cov = platform_to_base_covariance(T_world_platform_est, T_platform_base, fix.covariance)
    unobserved = ["rx", "ry"] + ([] if fix.heading_observed else ["rz"])
    rmse = float(np.sqrt(np.mean(fix.residuals**2))) if fix.residuals.size else 0.0
    quality: dict[str, Any] = {
        "estimator": method,
        "solver": "joint Gauss-Newton over all ranges"
        if method == "wls-t"
        else f"median of {method} fixes",
        "n_tags": len(L),
        "n_anchors": len(ids),
        "n_rounds": n_rounds,
        "n_ranges": int(sim.ranges.size),
        "n_rejected_robust_centre": int(rej.rejected.sum()),
        "n_rejected_residual": fix.n_ranges - fix.n_used,
        "n_used": fix.n_used,
        "n_nlos_simulated": int(sim.nlos.sum()),
        "n_occluded_links": 0 if occluded is None else int(occluded.sum()),
        "per_anchor_rms": dict(zip(ids, [float(v) for v in fix.per_anchor_rms], strict=True)),
        "calibration": cal.to_dict(ids),
        "std_xyz_yaw": [float(v) for v in np.sqrt(np.diag(fix.covariance))],
        "unobserved": unobserved,
        "unobserved_variance_rad2": UNOBSERVED_VARIANCE,
        "note": "level platform assumed: roll and pitch are not observed by UWB ranging; "
        "covariance: white range noise plus the calibration's remaining per-anchor error",
    }
    return BasePose(
        T_world_base=T_world_base_est,
        covariance=cov,
        method="uwb",
        residuals=fix.residuals[:, None],
        rmse=rmse,
        station=station_id,
        quality=quality,
    )
