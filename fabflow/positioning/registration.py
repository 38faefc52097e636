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
:mod:`fabflow.positioning.rigid_fit`, the tests as array kernels (all points
at once, nothing refitted) in :mod:`fabflow.positioning.registration_tests`;
:func:`fabflow.positioning.registration_batch.register_points_batch` solves
many problems of the same size at once.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from scipy import special

from fabflow.errors import InputError
from fabflow.positioning.adjustment_tests import ALPHA, TestResult
from fabflow.positioning.integrity import Integrity, identify, record, unchecked
from fabflow.positioning.prism_match import match_prisms
from fabflow.positioning.registration_tests import (
    Fits,
    LooTestArrays,
    PointTestArrays,
    as_test_result,
    leave_each_out,
    loo_f_test_arrays,
    point_test_arrays,
)
from fabflow.positioning.result import BasePose
from fabflow.positioning.rigid_fit import (
    NormalEquations,
    as_points,
    check_geometries,
    check_geometry,
    degenerate,
    normal_equations,
    principal_spreads,
)
from fabflow.positioning.small_linalg import inv_spd6


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
    check_geometries((P, M), ("points_base", "points_world"))
    if method not in ("closed_form", "optimize"):
        raise InputError(f"unknown method {method!r}; expected 'closed_form' or 'optimize'")
    known_sigma = point_cov is not None or sigma is not None
    if point_cov is not None:
        C = np.asarray(point_cov, dtype=float)
        if C.shape != (n, 3, 3) or not np.all(np.isfinite(C)):
            raise InputError(f"point_cov must be a finite ({n}, 3, 3) array, got {C.shape}")
        C = C + base_sigma**2 * np.eye(3)
        c_min = np.linalg.eigvalsh(C)[:, 0]
        if np.any(c_min <= 0):
            raise InputError("point_cov must be positive definite for every point")
        w = 3.0 / np.trace(C, axis1=1, axis2=2)
        w_max = 1.0 / c_min  # largest eigenvalue of each information matrix
    else:
        w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
        if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise InputError(f"weights must be {n} non-negative finite numbers, not all zero")
        s2 = (1.0 if sigma is None else sigma**2) + base_sigma**2
        # zero-weight points get a placeholder: they never enter the fit
        C = (s2 / np.where(w > 0, w, 1.0))[:, None, None] * np.eye(3)
        w_max = w / s2
    keep = w > 0
    if not keep.all():
        check_geometry(P[keep], "points_base with positive weight")
    identification: dict[str, Any] = {}
    if known_sigma and identify_prisms:
        order, identification = match_prisms(P, M, C, labels, alpha)
        M, C, w, w_max = M[order], C[order], w[order], w_max[order]
        keep = w > 0
    if point_cov is None:
        W = w_max[:, None, None] * np.eye(3)
    elif keep.all():
        W = np.linalg.inv(C)
    else:
        W = np.zeros_like(C)
        W[keep] = np.linalg.inv(C[keep])
    fits = Fits(P, M, w, W, w_max, method, refine=point_cov is not None)

    excluded: list[dict[str, Any]] = []
    integrity: Integrity
    final: tuple[NormalEquations, np.ndarray] | None = None
    if known_sigma:
        R, t, iters = fits.one(keep)
        everything = keep.all()
        tests, arrays, eq = _point_tests(
            P,
            M,
            W if everything else W[keep],
            R,
            t,
            keep,
            labels,
            alpha,
            w_max if everything else w_max[keep],
        )
        final = (eq, arrays.Ninv)
        outlier = outlier_report(tests, keep, arrays.bias)
        ambiguous: list[str] = []
        while reject_outlier and identify(tests) is not None:
            # every point the w-tests could blame is tried: left out, fitted again, tested
            trials = leave_each_out(fits, keep, labels, alpha)
            passing = [x for x in trials if x.passed]
            if len(passing) > 1:
                # several single points explain the misfit: the faulty one is not identified
                ambiguous = [labels[x.index] for x in passing]
                break
            if passing:
                chosen = passing[0]
            elif trials and keep.sum() > 4:
                # no single point explains it: leave out the one the w-test blames, go on
                k = identify(tests)
                assert k is not None
                i = int(np.flatnonzero(keep)[k])
                blamed = next((x for x in trials if x.index == i), None)
                if blamed is None:
                    break  # the rest would not span a plane: the pose stays failed
                chosen = blamed
            else:
                break
            i, keep, R, t, iters = chosen.index, chosen.keep, chosen.R, chosen.t, chosen.iters
            after, eq, Ninv = chosen.result()
            final = (eq, Ninv)
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
        sel = np.flatnonzero(keep)
        omega = w[sel] / s2
        loo: LooTestArrays | None = None
        if method == "closed_form" and len(sel) >= 4:
            # the leave-one-out stack holds the fit of all the points too
            loo = loo_f_test_arrays(P[sel], M[sel], omega, alpha)
            R, t, iters = loo.R, loo.t, 0
        else:
            R, t, iters = fits.one(keep)
            if len(sel) >= 4:
                loo = loo_f_test_arrays(P[sel], M[sel], omega, alpha, R, t)
        outlier = None if loo is None else _loo_outlier_test(loo, sel, n)
        if loo is not None:
            final = (loo.eq, loo.Ninv)
        if outlier is not None and outlier.flagged and reject_outlier:
            trial = keep.copy()
            trial[outlier.index] = False
            if not degenerate(principal_spreads(P[trial])):
                keep = trial
                R, t, iters = fits.one(keep)
                final = None
                excluded.append({"observation": labels[outlier.index], "w": None})
        integrity = relative_integrity(outlier, excluded, labels, alpha)
    if identification:
        integrity = integrity.with_checks(prism_identification=identification)
        if identification.get("reassigned"):
            integrity = replace(
                integrity,
                reason="; ".join(x for x in (identification["reassigned"], integrity.reason) if x),
            )

    if final is None:
        eq = normal_equations(R, t, P[keep], M[keep], W[keep])
        final = (eq, inv_spd6(eq.N))
    eq, cov = final
    residuals = M - (P @ R.T + t)
    r_in = residuals if keep.all() else residuals[keep]
    dof = 3 * len(r_in) - 6
    chi2 = float(np.einsum("ni,ni->", eq.v, eq.Wv))
    vf = chi2 / dof if dof > 0 else float("nan")
    if not known_sigma:
        # relative weights only: scale the covariance by the estimated variance
        cov = cov * (vf if dof > 0 else 0.0)
    T_world_base = np.eye(4)
    T_world_base[:3, :3] = R
    T_world_base[:3, 3] = t
    return Registration(
        T_world_base=T_world_base,
        covariance=0.5 * (cov + cov.T),
        residuals=residuals,
        rmse=math.sqrt(float(np.einsum("ni,ni->", r_in, r_in)) / len(r_in)),
        method=method,
        variance_factor=vf,
        outlier_test=outlier,
        rejected=tuple(int(i) for i in np.flatnonzero(~keep)),
        iterations=int(iters),
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
    The numbers of :func:`~fabflow.positioning.adjustment_tests.adjustment_test`, from
    :func:`~fabflow.positioning.registration_tests.point_test_arrays`.
    """
    sel = np.flatnonzero(keep)
    return _point_tests(P, M, np.linalg.inv(C[sel]), R, t, keep, labels, alpha)[0]


def _point_tests(
    P: np.ndarray,
    M: np.ndarray,
    W: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    keep: np.ndarray,
    labels: Sequence[str],
    alpha: float,
    w_max: np.ndarray | None = None,
) -> tuple[TestResult, PointTestArrays, NormalEquations]:
    """:func:`point_tests` from the information matrices ``W`` of the kept points (and
    their largest eigenvalues, when known), also returning the arrays and the fit's
    normal equations."""
    if keep.all():
        Pk, Mk, names = P, M, list(labels)
    else:
        sel = np.flatnonzero(keep)
        Pk, Mk, names = P[sel], M[sel], [labels[i] for i in sel]
    eq = normal_equations(R, t, Pk, Mk, W)
    arrays = point_test_arrays(eq, W, alpha, w_max)
    return as_test_result(arrays, names), arrays, eq


def outlier_report(
    tests: TestResult, keep: np.ndarray, bias: np.ndarray | None = None
) -> OutlierTest | None:
    """The per-point part of the tests in the form of :class:`OutlierTest`.

    ``bias``: the ``(k, 3)`` bias estimates of the kept points when at hand (else
    those of ``tests``).
    """
    n_points = len(tests.w) - 1
    if n_points < 4:
        return None
    stat = tests.w[:n_points] ** 2
    k = int(np.nanargmax(stat) if np.isnan(stat).any() else np.argmax(stat))
    threshold = float(tests.thresholds[k] ** 2)
    loo = np.stack(tests.bias[:n_points]) if bias is None else bias
    n = len(keep)
    if n_points == n:
        index, statistics, loo_residuals = k, stat, loo.copy()
    else:
        sel = np.flatnonzero(keep)
        index = int(sel[k])
        statistics = _scatter(stat, sel, n, np.nan)
        loo_residuals = _scatter(loo, sel, n, np.nan)
    return OutlierTest(
        index=index,
        flagged=bool(stat[k] > threshold),
        statistics=statistics,
        threshold=threshold,
        p_value=_chi2_3_sf(float(stat[k])),
        loo_residuals=loo_residuals,
        known_sigma=True,
    )


def _chi2_3_sf(x: float) -> float:
    """Survival function of chi-square with 3 degrees of freedom (closed form)."""
    return math.erfc(math.sqrt(0.5 * x)) + math.sqrt(2.0 * x / math.pi) * math.exp(-0.5 * x)


def _loo_outlier_test(loo: LooTestArrays, sel: np.ndarray, n: int) -> OutlierTest:
    """The leave-one-out F-test (noise level from the residuals) as an :class:`OutlierTest`."""
    stat = loo.statistics
    k = int(np.argmax(stat))
    dof = 3 * (len(sel) - 1) - 6
    everything = len(sel) == n
    return OutlierTest(
        index=k if everything else int(sel[k]),
        flagged=bool(stat[k] > loo.threshold),
        statistics=stat if everything else _scatter(stat, sel, n, np.nan),
        threshold=loo.threshold,
        p_value=float(special.fdtrc(3, dof, stat[k])),
        loo_residuals=loo.loo_residuals
        if everything
        else _scatter(loo.loo_residuals, sel, n, np.nan),
        known_sigma=False,
    )


def relative_integrity(
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
