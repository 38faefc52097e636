"""Many point registrations of the same size at once (Monte Carlo runs, sweeps, benchmarks).

:func:`register_points_batch` solves ``B`` problems of ``n`` matched points the
way :func:`fabflow.positioning.registration.register_points` solves one (with
the readings taken as matched and nothing left out: ``identify_prisms=False``,
``reject_outlier=False``): weighted Kabsch, Gauss-Newton on the full point
covariances, the 6x6 covariance and the tests (global test, w-tests of every
point and of scale, MDBs, protection level; or the leave-one-out F-test with
relative weights). Every step is a stacked array operation over the problems
(:mod:`fabflow.positioning.small_linalg` for the tiny matrices); the problems
go through in blocks of :data:`BLOCK` so that the temporaries stay in cache.
:meth:`BatchRegistration.registration` gives one problem's result as the
:class:`~fabflow.positioning.registration.Registration` the single solve returns.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import special

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning import registration_soa as soa
from fabflow.positioning.adjustment_tests import ALPHA
from fabflow.positioning.integrity import record
from fabflow.positioning.registration import (
    OutlierTest,
    Registration,
    outlier_report,
    relative_integrity,
)
from fabflow.positioning.registration_tests import (
    PointTestArrays,
    as_test_result,
    loo_f_test_arrays,
    tests_passed,
)
from fabflow.positioning.rigid_fit import degenerate, kabsch, normal_equations
from fabflow.positioning.small_linalg import inv_spd6, sym3_inv, sym3_pd
from fabflow.transforms.se3 import make_T

BLOCK = 4096
"""Problems solved together: large enough to amortise each array operation, small enough
that the temporaries of a block stay in cache."""


@dataclass(frozen=True, eq=False)
class BatchRegistration:
    """Results of ``B`` point registrations of ``n`` points (:func:`register_points_batch`).

    Attributes
    ----------
    T_world_base
        ``(B, 4, 4)`` poses of the robot base in the world (metres).
    covariance
        ``(B, 6, 6)`` covariances over ``[dx, dy, dz, rx, ry, rz]`` (fabflow convention).
    residuals
        ``(B, n, 3)`` measured minus fitted world positions (metres).
    rmse
        ``(B,)`` RMS of the 3D residual lengths (metres).
    variance_factor
        ``(B,)`` weighted residual sum of squares over ``3 n - 6``.
    iterations
        ``(B,)`` Gauss-Newton iterations.
    status
        ``(B,)`` ``"ok"`` or ``"failed"`` (the tests failed, or could not be run).
    known_sigma
        Whether the point covariances (or sigma) were known: the global and
        w-tests ran; otherwise the leave-one-out F-test.
    alpha
        Level of the tests.
    global_statistic, global_p_value
        ``(B,)`` global test ``v^T Q^-1 v`` and its p-value (NaN without known sigma).
    global_threshold
        Its critical value (chi-square, ``3 n - 6`` dof).
    w, w_thresholds, mdb
        ``(B, n + 1)`` w-test values, critical values and minimal detectable
        biases of the points and of scale (NaN without known sigma).
    protection_level
        ``(B, 2)`` horizontal and vertical protection level (metres; infinite
        when a fault could go unseen, NaN without known sigma).
    outlier_index
        ``(B,)`` the most suspicious point (-1 with fewer than 4 points).
    outlier_flagged
        ``(B,)`` whether it fails its test.
    outlier_statistics
        ``(B, n)`` chi-square(3) (known sigma) or F statistic of each point.
    outlier_threshold
        ``(B,)`` critical value of those statistics.
    outlier_p_value
        ``(B,)`` p-value of the most suspicious point.
    loo_residuals
        ``(B, n, 3)`` each point measured minus predicted from the others (metres).
    tests
        The full test arrays with known sigma (MDBs, shifts, bias estimates), else None.
    """

    T_world_base: np.ndarray
    covariance: np.ndarray
    residuals: np.ndarray
    rmse: np.ndarray
    variance_factor: np.ndarray
    iterations: np.ndarray
    status: np.ndarray
    known_sigma: bool
    alpha: float
    global_statistic: np.ndarray
    global_threshold: float
    global_p_value: np.ndarray
    w: np.ndarray
    w_thresholds: np.ndarray
    mdb: np.ndarray
    protection_level: np.ndarray
    outlier_index: np.ndarray
    outlier_flagged: np.ndarray
    outlier_statistics: np.ndarray
    outlier_threshold: np.ndarray
    outlier_p_value: np.ndarray
    loo_residuals: np.ndarray
    tests: PointTestArrays | None = None

    def __len__(self) -> int:
        return int(self.T_world_base.shape[0])

    @property
    def passed(self) -> np.ndarray:
        """``(B,)`` whether each pose may be used."""
        return self.status == "ok"

    def registration(self, i: int, point_labels: list[str] | None = None) -> Registration:
        """Problem ``i`` as the :class:`Registration` that ``register_points`` returns for it.

        (``identify_prisms=False``, ``reject_outlier=False``; ``point_labels``
        name the points in the integrity record, ``"prism k"`` by default.)
        """
        n = self.residuals.shape[1]
        labels = point_labels or [f"prism {k}" for k in range(n)]
        keep = np.ones(n, dtype=bool)
        outlier: OutlierTest | None
        if self.known_sigma:
            assert self.tests is not None
            one = PointTestArrays(*(x if np.ndim(x) == 0 else x[i] for x in self.tests))
            tests = as_test_result(one, labels)
            outlier = outlier_report(tests, keep)
            integrity = record(tests, (), self.alpha)
        else:
            outlier = None
            if self.outlier_index[i] >= 0:
                outlier = OutlierTest(
                    index=int(self.outlier_index[i]),
                    flagged=bool(self.outlier_flagged[i]),
                    statistics=self.outlier_statistics[i].copy(),
                    threshold=float(self.outlier_threshold[i]),
                    p_value=float(self.outlier_p_value[i]),
                    loo_residuals=self.loo_residuals[i].copy(),
                    known_sigma=False,
                )
            integrity = relative_integrity(outlier, [], labels, self.alpha)
        return Registration(
            T_world_base=self.T_world_base[i].copy(),
            covariance=self.covariance[i].copy(),
            residuals=self.residuals[i].copy(),
            rmse=float(self.rmse[i]),
            method="closed_form",
            variance_factor=float(self.variance_factor[i]),
            outlier_test=outlier,
            iterations=int(self.iterations[i]),
            integrity=integrity,
        )


def register_points_batch(
    points_base: Any,
    points_world: Any,
    weights: Any = None,
    *,
    point_cov: Any = None,
    sigma: float | None = None,
    base_sigma: float = 0.0,
    alpha: float = ALPHA,
) -> BatchRegistration:
    """Localize ``B`` robot bases from ``n`` matched prism points each, all at once.

    Problem ``b`` gets what ``register_points(points_base[b], points_world[b],
    weights[b], point_cov=point_cov[b], sigma=sigma, base_sigma=base_sigma,
    alpha=alpha, identify_prisms=False)`` returns (see
    :meth:`BatchRegistration.registration`): the same pose, covariance and
    test values to rounding, the same decisions.

    Parameters
    ----------
    points_base
        ``(B, n, 3)`` or ``(n, 3)`` (the same for every problem) prism positions in
        the robot base frame (metres), n >= 3.
    points_world
        ``(B, n, 3)`` the prisms measured in the world frame (metres).
    weights
        ``(B, n)`` or ``(n,)`` positive relative weights (used without ``point_cov``).
    point_cov
        ``(B, n, 3, 3)`` or ``(n, 3, 3)`` covariances of the measured points (m^2, world).
    sigma
        Isotropic standard deviation of the measured points (metres) without
        ``point_cov``; without either the noise level comes from the residuals
        (leave-one-out F-test, no global test).
    base_sigma
        Isotropic standard deviation of the base-frame points (metres).
    alpha
        Level of the tests.

    Returns
    -------
    BatchRegistration

    Raises
    ------
    InputError
        Arrays of the wrong shape, non-finite values, weights not positive,
        covariances not positive definite (naming the problem and the point).
    LocalizationError
        Fewer than 3 points, or a problem whose points are (nearly) collinear.
    """
    M = _array(points_world, "points_world")
    if M.ndim != 3 or M.shape[-1] != 3:
        raise InputError(f"points_world must have shape (B, n, 3), got {M.shape}")
    B, n = M.shape[:2]
    if B == 0:
        raise InputError("points_world holds no problems (shape (0, n, 3))")
    P = _array(points_base, "points_base")
    if P.shape not in ((n, 3), (B, n, 3)):
        raise InputError(f"points_base must have shape ({n}, 3) or ({B}, {n}, 3), got {P.shape}")
    if n < 3:
        raise LocalizationError(f"points_base: need at least 3 points to fix a pose, got {n}")
    _finite(P, "points_base")
    _finite(M, "points_world")
    if P.ndim == 2:
        _geometry(P[None], "points_base", 0)
    known_sigma = point_cov is not None or sigma is not None
    C: np.ndarray | None = None
    w: np.ndarray | None = None
    if point_cov is not None:
        C = _array(point_cov, "point_cov")
        if C.shape not in ((n, 3, 3), (B, n, 3, 3)):
            raise InputError(f"point_cov must have shape ({B}, {n}, 3, 3), got {C.shape}")
        _finite(C, "point_cov")
        C = np.broadcast_to(C + base_sigma**2 * np.eye(3), (B, n, 3, 3))
        s2 = 1.0
    else:
        w = np.ones(n) if weights is None else _array(weights, "weights")
        if w.shape not in ((n,), (B, n)):
            raise InputError(f"weights must have shape ({n},) or ({B}, {n}), got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w <= 0):
            raise InputError(
                "weights must be positive finite numbers (register_points leaves "
                "zero-weight points out)"
            )
        w = np.broadcast_to(w, (B, n))
        s2 = (1.0 if sigma is None else sigma**2) + base_sigma**2
    blocks = []
    for start in range(0, B, BLOCK):
        part = slice(start, min(start + BLOCK, B))
        Pb = P if P.ndim == 2 else P[part]
        if P.ndim == 3:
            _geometry(Pb, "points_base", start)
        if C is None:
            _geometry(M[part], "points_world", start)
        if C is not None:
            blocks.append(_known_block(Pb, M[part], C[part], start, alpha))
        elif known_sigma:
            assert w is not None
            blocks.append(_sigma_block(Pb, M[part], w[part], s2, alpha))
        else:
            assert w is not None
            blocks.append(_relative_block(Pb, M[part], w[part] / s2, alpha))
    fields = {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0] if k != "tests"}
    tests = None
    if known_sigma:
        parts = [b["tests"] for b in blocks]
        tests = PointTestArrays(
            *(x[0] if np.ndim(x[0]) == 0 else np.concatenate(x) for x in zip(*parts, strict=True))
        )
    return BatchRegistration(
        **fields,
        known_sigma=known_sigma,
        alpha=alpha,
        global_threshold=tests.threshold if tests is not None else np.nan,
        tests=tests,
    )


def _array(a: Any, name: str) -> np.ndarray:
    try:
        return np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be an array of numbers") from None


def _finite(a: np.ndarray, name: str) -> None:
    """Refuse NaN or infinity, naming the first problem (and point) that has one."""
    if np.isfinite(a.sum()):
        return
    bad = ~np.isfinite(a)
    if not bad.any():
        return  # the sum overflowed, the numbers are finite
    where = np.argwhere(bad)[0]
    index = "".join(f"[{int(i)}]" for i in where[: a.ndim - (1 if name != "point_cov" else 2)])
    raise InputError(f"{name}{index} is not finite")


def _geometry(points: np.ndarray, name: str, start: int) -> None:
    """Refuse problems whose points ``(B, n, 3)`` cannot fix a pose, naming the first one."""
    _refuse_degenerate(soa.spreads(soa.point_vectors(points)), points.shape[1], name, start)


def _refuse_degenerate(spreads: np.ndarray, n: int, name: str, start: int) -> None:
    bad = degenerate(spreads)
    if bad.any():
        k = int(np.argmax(bad))
        s = spreads[k]
        label = name if len(spreads) == 1 and start == 0 else f"{name}[{start + k}]"
        raise LocalizationError(
            f"{label}: the {n} points are (nearly) collinear or coincident "
            f"(principal spreads {s[0]:.4g} m, {s[1]:.3g} m); the rotation about their "
            "line is undetermined. Use points that span a plane."
        )


def _known_block(
    P: np.ndarray, M: np.ndarray, C: np.ndarray, start: int, alpha: float
) -> dict[str, Any]:
    """A block of problems with point covariances: Kabsch, Gauss-Newton, the tests."""
    p, m = soa.point_vectors(P), soa.point_vectors(M)
    _refuse_degenerate(soa.spreads(m), M.shape[1], "points_world", start)
    Cs = soa.point_sym(C)
    pd = sym3_pd(Cs)
    if not pd.all():
        i, b = np.argwhere(~pd)[0]
        raise InputError(f"point_cov[{start + b}][{i}] must be positive definite")
    W = sym3_inv(Cs)
    R, t = soa.kabsch(p, m, 3.0 / (Cs[0] + Cs[3] + Cs[5]))
    R, t, iters = soa.gauss_newton(R, t, p, m, W)
    return _tested(p, m, W, Cs, R, t, iters, alpha)


def _sigma_block(
    P: np.ndarray, M: np.ndarray, w: np.ndarray, s2: float, alpha: float
) -> dict[str, Any]:
    """A block of problems with isotropic known noise: Kabsch, then the tests."""
    p, m = soa.point_vectors(P), soa.point_vectors(M)
    wt = np.ascontiguousarray(w.T)
    omega = wt / s2
    zero = np.zeros_like(omega)
    R, t = soa.kabsch(p, m, wt)
    iters = np.zeros(M.shape[0], dtype=int)
    W = (omega, zero, zero, omega, zero, omega)
    c = 1.0 / omega
    return _tested(p, m, W, (c, zero, zero, c, zero, c), R, t, iters, alpha)


def _tested(
    p: soa.Vec3,
    m: soa.Vec3,
    W: soa.Sym3,
    C: soa.Sym3,
    R: soa.Mat3,
    t: soa.Vec3,
    iters: np.ndarray,
    alpha: float,
) -> dict[str, Any]:
    """The covariance and the adjustment tests of a block of fits with known noise
    (information ``W`` and covariance ``C`` of the points)."""
    n, B = m[0].shape
    eq = soa.normal(R, t, p, m, W)
    tests = soa.point_tests(eq, W, C, alpha)
    passed = tests_passed(tests)
    stat = tests.w[:, :n] ** 2
    k = np.argmax(np.where(np.isnan(stat), -np.inf, stat), axis=-1)
    stat_k = np.take_along_axis(stat, k[:, None], -1)[:, 0]
    thr_k = np.take_along_axis(tests.thresholds, k[:, None], -1)[:, 0] ** 2
    shift = np.where(np.isnan(tests.shift), np.inf, tests.shift)
    untested = n < 4
    cov = tests.Ninv
    res, rmse = soa.residuals(R, t, p, m)
    return {
        "T_world_base": soa.pose_matrices(R, t),
        "residuals": soa.stack_points(res),
        "rmse": rmse,
        "variance_factor": tests.statistic / (3 * n - 6),
        "covariance": 0.5 * (cov + np.swapaxes(cov, -1, -2)),
        "iterations": iters.astype(int),
        "status": np.where(passed, "ok", "failed").astype("<U6"),
        "global_statistic": tests.statistic,
        "global_p_value": tests.p_value,
        "w": tests.w,
        "w_thresholds": tests.thresholds,
        "mdb": tests.mdb,
        "protection_level": shift.max(axis=1),
        "outlier_index": np.full(B, -1) if untested else k,
        "outlier_flagged": np.zeros(B, bool) if untested else stat_k > thr_k,
        "outlier_statistics": np.full((B, n), np.nan) if untested else stat,
        "outlier_threshold": np.full(B, np.nan) if untested else thr_k,
        "outlier_p_value": np.full(B, np.nan) if untested else special.chdtrc(3, stat_k),
        "loo_residuals": np.full((B, n, 3), np.nan) if untested else tests.bias,
        "tests": tests,
    }


def _relative_block(P: np.ndarray, M: np.ndarray, w: np.ndarray, alpha: float) -> dict[str, Any]:
    """A block of problems with relative weights: Kabsch and the leave-one-out F-test."""
    B, n = M.shape[:2]
    nan = np.full(B, np.nan)
    if n >= 4:
        loo = loo_f_test_arrays(P, M, w, alpha)
        R, t, eq, Ninv = loo.R, loo.t, loo.eq, loo.Ninv
        stat = loo.statistics
        k = np.argmax(stat, axis=-1)
        stat_k = np.take_along_axis(stat, k[:, None], -1)[:, 0]
        flagged = stat_k > loo.threshold
        p_value = special.fdtrc(3, 3 * (n - 1) - 6, stat_k)
        loo_residuals = loo.loo_residuals
        threshold = np.full(B, loo.threshold)
        status = np.where(flagged, "failed", "ok")
    else:
        R, t = kabsch(P, M, w)
        eq = normal_equations(R, t, P, M, w[..., None, None] * np.eye(3))
        Ninv = inv_spd6(eq.N)
        stat, k, flagged, p_value = np.full((B, n), np.nan), np.full(B, -1), nan < 0, nan
        loo_residuals = np.full((B, n, 3), np.nan)
        threshold = nan
        status = np.full(B, "failed")
    chi2 = np.einsum("bni,bni->b", eq.v, eq.Wv)
    residuals = M - (P @ np.swapaxes(R, -1, -2) + t[..., None, :])
    vf = chi2 / (3 * n - 6)
    cov = Ninv * vf[:, None, None]
    return {
        "T_world_base": make_T(R, t),
        "residuals": residuals,
        "rmse": np.sqrt(np.einsum("bni,bni->b", residuals, residuals) / n),
        "variance_factor": vf,
        "covariance": 0.5 * (cov + np.swapaxes(cov, -1, -2)),
        "iterations": np.zeros(B, dtype=int),
        "status": status.astype("<U6"),
        "global_statistic": nan,
        "global_p_value": nan,
        "w": np.full((B, n + 1), np.nan),
        "w_thresholds": np.full((B, n + 1), np.nan),
        "mdb": np.full((B, n + 1), np.nan),
        "protection_level": np.full((B, 2), np.nan),
        "outlier_index": k,
        "outlier_flagged": flagged,
        "outlier_statistics": stat,
        "outlier_threshold": threshold,
        "outlier_p_value": p_value,
        "loo_residuals": loo_residuals,
    }
