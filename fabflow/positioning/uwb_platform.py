"""The platform pose from UWB ranges of several tags: ``x, y, z, yaw`` and its covariance.

Tags sit at known lever arms on the platform (platform frame); every range of
every tag constrains the platform pose. :func:`locate_platform` estimates
``x, y, z, yaw`` (a level platform) jointly over all ranges by Gauss-Newton
(``wls-t``), or as the median of per-epoch fixes (``ls``, ``wls``), with
residual-based rejection; :func:`platform_to_base_covariance` moves the
covariance to the arm base. Metres and radians; anchors in the world frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.integrity import (
    ALPHA,
    Covariance,
    Hypothesis,
    Integrity,
    TestResult,
    adjustment_test,
    identify,
    record,
)
from fabflow.positioning.uwb import (
    COND_LIMIT,
    MIN_RANGE_FOR_WEIGHT,
    UNOBSERVED_VARIANCE,
    Method,
    Sigma,
    locate,
    sigma_of,
)
from fabflow.positioning.uwb_calibration import running_median


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
    integrity
        The tests of the fix (global test, w-test per anchor and per tag-anchor
        link, reliability), what was left out, and the geometry checks.
    converged
        Whether the final Gauss-Newton solve converged.
    """

    state: np.ndarray
    covariance: np.ndarray
    residuals: np.ndarray
    n_ranges: int
    n_used: int
    iterations: int
    heading_observed: bool
    per_anchor_rms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    integrity: Integrity | None = None
    converged: bool = True

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
    alpha: float = ALPHA,
    anchor_ids: Sequence[str] | None = None,
    base_lever: np.ndarray | None = None,
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
    alpha
        Level of the tests. The fix is tested with the global test and a w-test
        per anchor (a bias shared by all its ranges: a mis-surveyed anchor, an
        antenna delay, a wall in the way) and per tag-anchor link; while they fail,
        the worst anchor or link is left out and the pose solved again, as long
        as three anchors and the heading remain (:mod:`fabflow.positioning.integrity`).
    anchor_ids
        Anchor names for the integrity record (default ``A1``, ``A2``, ...).
    base_lever
        (3,) the arm base in the platform frame (metres): the protection level is
        given for the base, which a heading error moves too.

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
    s = sigma_of(sigma, np.maximum(d, MIN_RANGE_FOR_WEIGHT))
    ids = list(anchor_ids) if anchor_ids is not None else [f"A{j + 1}" for j in range(A.shape[0])]
    bias_sigma = (
        np.zeros(A.shape[0])
        if anchor_bias_sigma is None
        else np.asarray(anchor_bias_sigma, dtype=float)
    )
    lever = np.zeros(3) if base_lever is None else np.asarray(base_lever, dtype=float)
    use = np.ones(d.size, dtype=bool)
    left_out = np.zeros(d.size, dtype=bool)
    iterations, converged = 0, True
    excluded: list[dict[str, Any]] = []
    while True:
        if method == "wls-t" or not heading_observed or n_tags == 1:
            for _pass in range(2):
                state, iterations, converged = _platform_gn(
                    A, L, d[use], s[use], tag_idx[use], anc_idx[use], state, heading_prior,
                    max_iter,
                )  # fmt: skip
                res = d - _platform_h(A, L, state, tag_idx, anc_idx)
                keep = (np.abs(res) <= outlier_k * s) & ~left_out
                if np.array_equal(keep, use):
                    break
                use = keep
        tests = _platform_tests(
            A, L, d, s, tag_idx, anc_idx, use, state, heading_prior, heading_observed,
            bias_sigma, ids, lever, alpha,
        )  # fmt: skip
        k = identify(tests)
        if k is None:
            break
        drop = _hypothesis_ranges(tests.labels[k], ids, tag_idx, anc_idx)
        rest = use & ~drop
        if len(np.unique(anc_idx[rest])) < 3 or not _determined(
            A, L, s[rest], tag_idx[rest], anc_idx[rest], state, heading_prior, heading_observed
        ):
            break
        excluded.append(
            {
                "observation": tests.labels[k],
                "w": float(tests.w[k]),
                "threshold": float(tests.thresholds[k]),
            }
        )
        left_out |= drop
        use &= ~drop
    info = _platform_info(A, L, s[use], tag_idx[use], anc_idx[use], state, heading_prior)
    yaw_fixed = heading_observed
    if not yaw_fixed:
        info[3, :] = 0.0
        info[:, 3] = 0.0
        info[3, 3] = 1.0 / UNOBSERVED_VARIANCE
    ev = np.linalg.eigvalsh(info)
    determined = bool(ev[0] > ev[-1] / COND_LIMIT)
    if not determined and not excluded and use.all():
        raise LocalizationError("the tag and anchor geometry does not determine the platform pose")
    # ranges left out by the residual test can leave the pose undetermined: it fails below
    cov = np.linalg.inv(info) if determined else np.linalg.pinv(info) + np.diag(np.full(4, 1e6))
    if anchor_bias_sigma is not None:
        J = _platform_jac(A, L, state, tag_idx[use], anc_idx[use])
        if not yaw_fixed:
            J[:, 3] = 0.0
        G = cov @ (J / s[use][:, None] ** 2).T
        for j, sb in enumerate(bias_sigma):
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
    integrity = record(tests, excluded, alpha, _geometry(A[np.unique(anc_idx[use])], state))
    if not determined:
        integrity = integrity.failing(
            "the ranges left after the outlier and residual tests do not determine the pose"
        )
    elif not converged:
        integrity = integrity.failing(f"the pose did not converge in {max_iter} iterations")
    elif integrity.checks["outside_coverage_m"] > COVERAGE_MARGIN:
        integrity = integrity.failing(
            f"the platform stands {integrity.checks['outside_coverage_m']:.1f} m outside the "
            f"anchors' coverage (their convex hull in plan, PDOP "
            f"{integrity.checks['pdop']:.1f}): move anchors around the station"
        )
    return PlatformFix(
        state=state,
        covariance=cov,
        residuals=res[use],
        n_ranges=int(d.size),
        n_used=int(use.sum()),
        iterations=iterations,
        heading_observed=yaw_fixed,
        per_anchor_rms=per_anchor,
        integrity=integrity,
        converged=converged,
    )


COVERAGE_MARGIN = 0.5
"""How far (metres, in plan) a platform may stand outside the anchors' convex hull
before its fix fails: outside, the geometry degrades fast and the linearized
covariance no longer describes the error."""


def _platform_tests(
    A: np.ndarray,
    L: np.ndarray,
    d: np.ndarray,
    s: np.ndarray,
    tag_idx: np.ndarray,
    anc_idx: np.ndarray,
    use: np.ndarray,
    state: np.ndarray,
    heading_prior: tuple[float, float] | None,
    heading_observed: bool,
    bias_sigma: np.ndarray,
    ids: Sequence[str],
    lever: np.ndarray,
    alpha: float,
) -> TestResult:
    """The adjustment tests of a platform fix over the used ranges.

    Observations are the ranges, each with its white noise, plus the bias every
    range to one anchor shares (what the calibration leaves: ``bias_sigma``),
    so ``Q = diag(s^2) + U diag(bias_sigma^2) U^T``. Hypotheses: a bias of all
    ranges to one anchor (``anchor A3``) and, with two or more tags, of one
    tag-anchor link (``anchor A3 from tag 1``; tags are numbered from 0, as in
    the ranges file's ``tag`` column).
    """
    tg, an = tag_idx[use], anc_idx[use]
    J = _platform_jac(A, L, state, tg, an)
    if not heading_observed:
        J = J[:, :3]
    anchors = np.unique(an)
    U = (an[:, None] == anchors[None, :]).astype(float)
    Q = Covariance(
        diag=s[use] ** 2,
        low_rank=U if np.any(bias_sigma[anchors] > 0) else None,
        low_rank_var=np.maximum(bias_sigma[anchors], 1e-9) ** 2,
    )
    v = d[use] - _platform_h(A, L, state, tg, an)
    hyps = [Hypothesis(f"anchor {ids[j]}", U[:, k]) for k, j in enumerate(anchors)]
    n_tags = L.shape[0]
    if n_tags >= 2:
        for k in range(n_tags):
            for j in anchors:
                c = ((tg == k) & (an == j)).astype(float)
                if c.any():
                    hyps.append(Hypothesis(f"anchor {ids[j]} from tag {k}", c))
    R = _rotz(float(state[3]))
    G = np.zeros((3, J.shape[1]))
    G[:, :3] = np.eye(3)
    if heading_observed:
        G[:2, 3] = np.array([-(R @ lever)[1], (R @ lever)[0]])
    prior = None
    if heading_prior is not None and heading_observed:
        prior = np.zeros((4, 4))
        prior[3, 3] = 1.0 / heading_prior[1] ** 2
    return adjustment_test(J, Q, v, hyps, alpha, position_map=G, prior_information=prior)


def _determined(
    A: np.ndarray,
    L: np.ndarray,
    s: np.ndarray,
    tag_idx: np.ndarray,
    anc_idx: np.ndarray,
    state: np.ndarray,
    heading_prior: tuple[float, float] | None,
    heading_observed: bool,
) -> bool:
    """Whether these ranges still determine the platform pose (well-conditioned information)."""
    info = _platform_info(A, L, s, tag_idx, anc_idx, state, heading_prior)
    if not heading_observed:
        info = info[:3, :3]
    ev = np.linalg.eigvalsh(info)
    return bool(ev[0] > ev[-1] / COND_LIMIT)


def _hypothesis_ranges(
    label: str, ids: Sequence[str], tag_idx: np.ndarray, anc_idx: np.ndarray
) -> np.ndarray:
    """The ranges a hypothesis label names (``anchor A3`` or ``anchor A3 from tag 1``)."""
    words = label.split()
    j = list(ids).index(words[1])
    drop = anc_idx == j
    if len(words) > 2:
        drop &= tag_idx == int(words[-1])
    return drop


def _geometry(A: np.ndarray, state: np.ndarray) -> dict[str, float]:
    """PDOP of the anchors used at the platform, and how far outside their plan hull it stands."""
    p = state[:3]
    u = p - A
    u /= np.maximum(np.linalg.norm(u, axis=1), 1e-9)[:, None]
    info = u.T @ u
    pdop = float(np.sqrt(np.trace(np.linalg.pinv(info))))
    xy = A[:, :2]
    outside = 0.0
    if len(xy) >= 3 and np.linalg.matrix_rank(xy - xy.mean(axis=0)) == 2:
        hull = ConvexHull(xy)
        eq = hull.equations
        dist = eq[:, :2] @ p[:2] + eq[:, 2]
        if np.any(dist > 0):
            v = xy[hull.vertices]
            a, b = v, np.roll(v, -1, axis=0)
            ab = b - a
            tt = np.clip(np.einsum("ij,ij->i", p[:2] - a, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
            outside = float(np.min(np.linalg.norm(a + tt[:, None] * ab - p[:2], axis=1)))
    return {"pdop": pdop, "outside_coverage_m": outside}


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
) -> tuple[np.ndarray, int, bool]:
    """Damped Gauss-Newton on all ranges: the state, the iterations, whether it converged.

    Each step is scaled back (halved, up to 7 times) until it lowers the cost; the
    solve has converged when a step is negligible against its own uncertainty.
    """
    state = state.copy()

    def cost_of(x: np.ndarray) -> float:
        r = (d - _platform_h(A, L, x, tag_idx, anc_idx)) / s
        c = float(r @ r)
        if heading_prior is not None:
            c += (
                float(np.angle(np.exp(1j * (heading_prior[0] - x[3])))) ** 2 / heading_prior[1] ** 2
            )
        return c

    cost = cost_of(state)
    for iteration in range(1, max_iter + 1):
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
        if float(step @ M @ step) < 1e-10 or np.linalg.norm(step) < 1e-8:
            return state, iteration, True
        for scale in 0.5 ** np.arange(8):
            trial = state + scale * step
            new = cost_of(trial)
            if new <= cost:
                state, cost = trial, new
                break
        else:
            return state, iteration, False
    return state, max_iter, False


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


def heading_from_motion(fix_xy: np.ndarray, min_travel: float = 0.3, window: int = 31) -> float:
    """Heading (rad) of the first displacement longer than ``min_travel`` metres.

    ``fix_xy`` are (N, 2) position fixes in time order (NaN allowed). They are
    smoothed by a running median of ``window`` fixes first, so single noisy
    fixes do not trigger; the displacement is measured from the median of the
    first ``window`` fixes.
    """

    xy = np.asarray(fix_xy, dtype=float)
    if np.sum(np.all(np.isfinite(xy), axis=1)) < window:
        raise LocalizationError("too few position fixes to take the heading from the motion")
    smooth = running_median(xy, window)
    start = np.nanmedian(xy[:window], axis=0)
    dist = np.linalg.norm(smooth - start, axis=1)
    moved = np.flatnonzero(dist > min_travel)
    if moved.size == 0:
        raise LocalizationError(
            "one tag and an IMU: the heading comes from the motion, but the tag never moved "
            f"more than {min_travel} m; add a second tag"
        )
    d = smooth[moved[0]] - start
    return float(math.atan2(d[1], d[0]))
