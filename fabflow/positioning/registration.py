"""Arbitrary-point localization (paper 001, eqs 7-8): base pose from matched prism points.

A prism on the robot's tool is moved to known points ``p_i`` of the robot base
frame (from forward kinematics); the total station measures each one, giving
``m_i`` in the world. :func:`register_points` finds the rigid motion taking
the ``p_i`` onto the ``m_i``: closed form by weighted Kabsch/Umeyama
(reflection-safe); with per-point covariances (a total station's are
needle-shaped along the line of sight) a few Gauss-Newton steps then minimise
the full Mahalanobis cost; ``method="optimize"`` solves the paper's constrained
problem over ``(O, X, Y)`` with SLSQP instead. The result carries the 6x6
covariance (fabflow convention, see :mod:`fabflow.positioning.result`),
residuals, RMSE and a leave-one-out test for a single bad prism reading
(:class:`OutlierTest`). The solvers themselves are in
:mod:`fabflow.positioning.rigid_fit`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from scipy import special

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
    unchecked,
)
from fabflow.positioning.prism_match import match_prisms
from fabflow.positioning.result import BasePose
from fabflow.positioning.rigid_fit import (
    as_points,
    check_geometry,
    kabsch,
    normal_matrices,
    optimize_registration,
    point_jacobians,
    refine_registration,
)
from fabflow.transforms.se3 import make_T


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
    integrity
        The tests of the final fit (global test, w-tests of every point and of
        the scale, reliability) and the prism identification.
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
    integrity: Integrity | None = None

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
            integrity=self.integrity,
        )


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
    J = point_jacobians(R, P)
    N = normal_matrices(J, W)
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
    alpha: float = ALPHA,
    point_labels: Sequence[str] | None = None,
    identify_prisms: bool = True,
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
        Leave out the point the tests identify and fit again, while the tests
        fail and the remaining points still span a plane (Baarda's iterative
        data snooping); otherwise a failed test is only reported.
    alpha
        Significance level of the tests (the w-tests are Bonferroni-corrected).
    point_labels
        Names of the points (``"prism P3"``), used in the integrity record.
    identify_prisms
        With known covariances and at least 4 points, check that the readings
        belong to the points by their distances, and reassign a swap
        (:func:`~fabflow.positioning.prism_match.match_prisms`).

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
    P = as_points(points_base, "points_base")
    M = as_points(points_world, "points_world", n=P.shape[0])
    n = P.shape[0]
    labels = list(point_labels) if point_labels is not None else [f"prism {i}" for i in range(n)]
    if len(labels) != n:
        raise InputError(f"point_labels must name the {n} points, got {len(labels)}")
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
    identification: dict[str, Any] = {}
    if known_sigma and identify_prisms:
        order, identification = match_prisms(P, M, C, labels, alpha)
        M, C, w = M[order], C[order], w[order]
        keep = w > 0
    W = np.zeros_like(C)
    W[keep] = np.linalg.inv(C[keep])

    def solve(sel: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        if method == "optimize":
            return optimize_registration(P[sel], M[sel], w[sel])
        R, t, iters = (*kabsch(P[sel], M[sel], w[sel]), 0)
        if point_cov is not None:
            return refine_registration(R, t, P[sel], M[sel], W[sel])
        return R, t, iters

    R, t, iters = solve(keep)
    excluded: list[dict[str, Any]] = []
    integrity: Integrity
    if known_sigma:
        tests = point_tests(P, M, C, R, t, keep, labels, alpha)
        outlier = _outlier_report(tests, keep)
        ambiguous: list[str] = []
        while reject_outlier and identify(tests) is not None:
            # every point the w-tests could blame is tried: left out, fitted again, tested
            trials = []
            for i in np.flatnonzero(keep):
                trial = keep.copy()
                trial[i] = False
                if not _spans_plane(P[trial]):
                    continue
                fit = solve(trial)
                trials.append((i, trial, fit, point_tests(P, M, C, *fit[:2], trial, labels, alpha)))
            passing = [x for x in trials if x[3].passed]
            if len(passing) > 1:
                # several single points explain the misfit: the faulty one is not identified
                ambiguous = [labels[x[0]] for x in passing]
                break
            if passing:
                i, keep, (R, t, iters), after = passing[0]
            elif trials and keep.sum() > 4:
                # no single point explains it: leave out the one the w-test blames, go on
                k = identify(tests)
                assert k is not None
                i = int(np.flatnonzero(keep)[k])
                blamed = next((x for x in trials if x[0] == i), None)
                if blamed is None:
                    break  # the rest would not span a plane: the pose stays failed
                i, keep, (R, t, iters), after = blamed
            else:
                break
            k = tests.labels.index(labels[i])
            excluded.append(
                {
                    "observation": labels[i],
                    "w": float(tests.w[k]),
                    "threshold": float(tests.thresholds[k]),
                    "others_explain_it": len(passing) == 0,
                }
            )
            tests = after
        integrity = record(tests, excluded, alpha)
        if ambiguous:
            integrity = integrity.failing(
                "the misfit is explained by leaving out any one of "
                + ", ".join(ambiguous)
                + ": the faulty reading cannot be identified"
            )
    else:
        outlier = _loo_outliers(P, M, W, R, t, keep, alpha)
        if outlier is not None and outlier.flagged and reject_outlier:
            trial = keep.copy()
            trial[outlier.index] = False
            if _spans_plane(P[trial]):
                keep = trial
                R, t, iters = solve(keep)
                excluded.append({"observation": labels[outlier.index], "w": None})
        integrity = _relative_integrity(outlier, excluded, labels, alpha)
    if identification:
        integrity = integrity.with_checks(prism_identification=identification)
        if identification.get("reassigned"):
            integrity = replace(
                integrity,
                reason="; ".join(x for x in (identification["reassigned"], integrity.reason) if x),
            )

    J = point_jacobians(R, P[keep])
    info = normal_matrices(J, W[keep]).sum(axis=0)
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
        outlier_test=outlier,
        rejected=tuple(int(i) for i in np.flatnonzero(~keep)),
        iterations=iters,
        integrity=integrity,
    )


def point_tests(
    P: np.ndarray,
    M: np.ndarray,
    C: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    keep: np.ndarray,
    labels: Sequence[str],
    alpha: float,
) -> TestResult:
    """The adjustment tests of a point registration (the points in ``keep``).

    Observations are the measured points (world, metres) with covariances ``C``;
    the parameters the pose error ``[d, r]``. The hypotheses are one per point
    (a bias of its three coordinates: chi-square(3), the leave-one-out test) and
    a scale error between the instrument and the robot geometry (a wrong
    distance unit or a robot model of the wrong size), which cannot be left out.
    """
    sel = np.flatnonzero(keep)
    n = len(sel)
    A = point_jacobians(R, P[sel]).reshape(3 * n, 6)
    v = (M[sel] - (P[sel] @ R.T + t)).reshape(-1)
    hyps = [Hypothesis(labels[i], np.kron(np.eye(n)[:, [k]], np.eye(3))) for k, i in enumerate(sel)]
    hyps.append(
        Hypothesis(
            "scale (instrument vs robot)", (P[sel] @ R.T).reshape(-1), excludable=False, unit=""
        )
    )
    return adjustment_test(A, Covariance(blocks=C[sel]), v, hyps, alpha)


def _outlier_report(tests: TestResult, keep: np.ndarray) -> OutlierTest | None:
    """The per-point part of the tests in the form of :class:`OutlierTest`."""
    n_points = len(tests.w) - 1
    if n_points < 4:
        return None
    sel = np.flatnonzero(keep)
    stat = tests.w[:n_points] ** 2
    k = int(np.nanargmax(stat))
    threshold = float(tests.thresholds[k] ** 2)
    n = len(keep)
    return OutlierTest(
        index=int(sel[k]),
        flagged=bool(stat[k] > threshold),
        statistics=_scatter(stat, sel, n, np.nan),
        threshold=threshold,
        p_value=float(special.chdtrc(3, stat[k])),
        loo_residuals=_scatter(np.stack(tests.bias[:n_points]), sel, n, np.nan),
        known_sigma=True,
    )


def _loo_outliers(
    P: np.ndarray,
    M: np.ndarray,
    W: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    keep: np.ndarray,
    alpha: float,
) -> OutlierTest | None:
    """The leave-one-out F-test when the noise level is estimated from the residuals."""
    sel = np.flatnonzero(keep)
    test = _loo_test(P[keep], M[keep], W[keep], R, t, False, alpha)
    if test is None:
        return None
    n = len(keep)
    return OutlierTest(
        index=int(sel[test.index]),
        flagged=test.flagged,
        statistics=_scatter(test.statistics, sel, n, np.nan),
        threshold=test.threshold,
        p_value=test.p_value,
        loo_residuals=_scatter(test.loo_residuals, sel, n, np.nan),
        known_sigma=False,
    )


def _relative_integrity(
    test: OutlierTest | None,
    excluded: list[dict[str, Any]],
    labels: Sequence[str],
    alpha: float,
) -> Integrity:
    """Integrity with relative weights only: no global test, the F-test identifies."""
    note = {"noise": "estimated from the residuals: no global test, F-test per point"}
    if test is None:
        return unchecked("fewer than 4 points and no known noise level: untested", alpha, **note)
    if test.flagged and not excluded:
        return Integrity(
            status="failed",
            reason=f"{labels[test.index]} fails the F-test (p = {test.p_value:.2g})",
            alpha=alpha,
            checks=note,
        )
    return Integrity(
        status="excluded" if excluded else "ok",
        reason="left out " + labels[test.index] if excluded else "",
        alpha=alpha,
        excluded=tuple(excluded),
        checks=note,
    )
