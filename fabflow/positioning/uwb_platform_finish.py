"""The last step of a standing platform's UWB fix: covariance, residuals and the record.

:func:`finish_fixes` turns final solutions (after the tests and any exclusions,
:mod:`fabflow.positioning.uwb_platform`) into :class:`PlatformFix` es: the
covariance of ``x, y, z, yaw`` with the anchors' remaining calibration error, each
anchor's RMS residual, the geometry checks (PDOP, distance outside the anchors'
plan hull) and the integrity record. Fixes of one shape (the same anchors and
links used) are finished in one stacked solve: a simulated run's visits.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from fabflow.errors import LocalizationError
from fabflow.positioning.adjustment_tests import TestResult
from fabflow.positioning.integrity import Integrity, record
from fabflow.positioning.uwb import COND_LIMIT, UNOBSERVED_VARIANCE
from fabflow.positioning.uwb_coverage import COVERAGE_MARGIN, geometry_checks
from fabflow.positioning.uwb_platform_adjustment import PlatformAdjustment
from fabflow.positioning.uwb_platform_model import (
    UNDETERMINED,
    information_of,
    jacobians_many,
)
from fabflow.positioning.uwb_platform_model import rotz as _rotz


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
        Ranges given (finite), and used: all but those the tests left out
        (``integrity.excluded``).
    iterations
        Gauss-Newton iterations of the final solve.
    heading_observed
        Whether the yaw is determined by the measurements (or a prior).
    per_anchor_rms
        (n_anchors,) RMS residual of the used ranges per anchor (metres); NaN for
        an anchor none of whose ranges is used (write it as ``None``).
    integrity
        The tests of the fix (global test, w-test per anchor and per tag-anchor
        link, reliability), what was left out, and the geometry checks.
    converged
        Whether the final Gauss-Newton solve converged.
    mirror_search
        ``(adjustment, links used, state, tests, reason recorded)`` of the mirror
        checks still to be made (:func:`finish_mirror_searches`) when
        :func:`locate_platform` was asked to leave them to the caller, else ``None``.
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
    mirror_search: tuple[PlatformAdjustment, np.ndarray, np.ndarray, TestResult, str] | None = None

    @property
    def T(self) -> np.ndarray:
        """4x4 platform pose (``T_frame_platform``)."""
        T = np.eye(4)
        T[:3, :3] = _rotz(float(self.state[3]))
        T[:3, 3] = self.state[:3]
        return T


class Final(NamedTuple):
    """A final solution to finish (:func:`finish_fixes`).

    ``ranges``: every finite range (metres) and its link (index into ``adj``'s
    links); ``use``: the links used; ``excluded``: what the tests left out on the
    way; ``problem``: why the exclusions stopped, if they failed.
    """

    adj: PlatformAdjustment
    ranges: tuple[np.ndarray, np.ndarray]
    use: np.ndarray
    state: np.ndarray
    tests: TestResult
    excluded: list[dict[str, Any]]
    problem: str
    iterations: int
    converged: bool


def finish_fixes(finals: Sequence[Final]) -> list[PlatformFix]:
    """The fixes of final solutions: covariance, residuals, integrity record and checks.

    Raises
    ------
    LocalizationError
        For the first solution, in order, that left nothing out and whose ranges
        do not determine the pose.
    """
    groups: dict[tuple[Any, ...], list[int]] = {}
    for i, f in enumerate(finals):
        adj = f.adj
        key = (
            adj.anchors.tobytes(), adj.lever_arms.tobytes(), adj.tag_idx.tobytes(),
            adj.anc_idx.tobytes(), f.use.tobytes(), adj.heading_observed, adj.heading_prior,
            bool(np.any(adj.bias_sigma > 0)),
        )  # fmt: skip
        groups.setdefault(key, []).append(i)
    covariance: list[np.ndarray] = [np.zeros((4, 4))] * len(finals)
    predicted: list[np.ndarray] = [np.zeros(0)] * len(finals)
    determined = np.zeros(len(finals), dtype=bool)
    geometry = np.zeros((len(finals), 2))
    for members in groups.values():
        cov, ok, pdop, outside, ranges = _covariances([finals[i] for i in members])
        for n, i in enumerate(members):
            covariance[i], determined[i], geometry[i] = cov[n], ok[n], (pdop[n], outside[n])
            predicted[i] = ranges[n]
    for i, f in enumerate(finals):
        if not determined[i] and not f.excluded:
            raise LocalizationError(UNDETERMINED)
    return [
        _fix(f, covariance[i], bool(determined[i]), *geometry[i], predicted[i])
        for i, f in enumerate(finals)
    ]


def _covariances(
    finals: Sequence[Final],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Covariances ``(n, 4, 4)``, whether the pose is determined, PDOPs, distances
    outside the anchors' plan hull and every link's predicted range ``(n, m)``
    (metres) of final solutions of one shape."""
    adj, use = finals[0].adj, finals[0].use
    A = adj.anchors
    an = adj.anc_idx[use]
    states = np.stack([f.state for f in finals])
    J_all, predicted = jacobians_many(
        np.stack([f.adj.anchors[f.adj.anc_idx] for f in finals]),
        np.stack([f.adj.lever_arms for f in finals]),
        states,
        adj.tag_idx,
    )
    J = J_all[:, use]
    s = np.stack([f.adj.s[use] for f in finals])
    info = information_of(J, s, adj.heading_prior)
    if not adj.heading_observed:
        info[:, 3, :] = 0.0
        info[:, :, 3] = 0.0
        info[:, 3, 3] = 1.0 / UNOBSERVED_VARIANCE
    ev = np.linalg.eigvalsh(info)
    determined = ev[:, 0] > ev[:, -1] / COND_LIMIT
    cov = np.empty_like(info)
    if determined.any():
        cov[determined] = np.linalg.inv(info[determined])
    if not determined.all():
        cov[~determined] = np.linalg.pinv(info[~determined]) + np.diag(np.full(4, 1e6))
    bias = np.stack([f.adj.bias_sigma for f in finals])
    if np.any(bias > 0):
        if not adj.heading_observed:
            J = np.where(np.arange(4) < 3, J, 0.0)  # without the heading column
        G = cov @ np.swapaxes(J / s[..., None] ** 2, 1, 2)
        g = G @ (an[:, None] == np.arange(len(A))[None, :]).astype(float)
        cov = cov + (g * bias[:, None, :] ** 2) @ np.swapaxes(g, 1, 2)
    pdop, outside = geometry_checks(A[adj.anchors_used(use)], states)
    return cov, determined, pdop, outside, predicted


def _fix(
    f: Final,
    cov: np.ndarray,
    determined: bool,
    pdop: float,
    outside: float,
    predicted: np.ndarray,
) -> PlatformFix:
    """One finished fix: residuals, per-anchor RMS and the integrity record, from its
    covariance, geometry checks and every link's predicted range (metres)."""
    adj, use, state = f.adj, f.use, f.state
    A = adj.anchors
    d, link = f.ranges
    an = adj.anc_idx[use]
    # squares of the ranges' residuals: their scatter about the link mean, plus the mean's
    squares = adj.raw_sq_dev[use] + adj.count[use] * (adj.raw_mean[use] - predicted[use]) ** 2
    n_used = np.bincount(an, weights=adj.count[use], minlength=len(A))
    ss = np.bincount(an, weights=squares, minlength=len(A))
    per_anchor = np.where(n_used > 0, np.sqrt(ss / np.maximum(n_used, 1)), np.nan)
    checks: dict[str, Any] = {"pdop": float(pdop), "outside_coverage_m": float(outside)}
    integrity = record(f.tests, f.excluded, adj.alpha, checks)
    # the mirror checks come at the end (finish_mirror_searches: many fixes' at once);
    # what the records below add does not depend on them
    search = (adj, use, state, f.tests, integrity.reason) if integrity.status != "failed" else None
    if f.problem:
        integrity = integrity.failing(f.problem)
    if not determined:
        integrity = integrity.failing("the ranges left out leave the pose undetermined")
    elif not f.converged:
        integrity = integrity.failing(f"the pose did not converge in {adj.max_iter} iterations")
    elif integrity.checks["outside_coverage_m"] > COVERAGE_MARGIN:
        integrity = integrity.failing(
            f"the platform stands {integrity.checks['outside_coverage_m']:.1f} m outside the "
            f"anchors' coverage (their convex hull in plan, PDOP "
            f"{integrity.checks['pdop']:.1f}): move anchors around the station"
        )
    state = state.copy()
    state[3] = (state[3] + np.pi) % (2 * np.pi) - np.pi
    return PlatformFix(
        state=state,
        covariance=cov,
        residuals=d[use[link]] - predicted[link[use[link]]],
        n_ranges=adj.n_ranges(np.ones(adj.d.size, dtype=bool)),
        n_used=adj.n_ranges(use),
        iterations=f.iterations,
        heading_observed=adj.heading_observed,
        per_anchor_rms=per_anchor,
        integrity=integrity,
        converged=f.converged,
        mirror_search=search,
    )
