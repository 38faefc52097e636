"""The tests of a point registration as array kernels, for one problem or a batch at once.

:func:`point_test_arrays` is :func:`fabflow.positioning.adjustment_tests.adjustment_test`
specialised to matched points (block-diagonal covariance, one three-column
hypothesis per point and one for scale): the same global test, w-tests, MDBs
and base shifts, with every per-point quantity a 3x3 matrix computed for all
points (and all problems) in a few stacked operations instead of a loop over
hypotheses. :func:`loo_f_test_arrays` is the leave-one-out test for relative
weights (noise level from the residuals): the fit without each point comes
from one stack of rank-one downdated Kabsch problems
(:func:`fabflow.positioning.rigid_fit.kabsch_leave_one_out`), its predicted
covariance from the full fit's normal matrix (Woodbury), so nothing is refitted.
:func:`leave_each_out` refits without each point in turn, all at once, for the
data snooping of :func:`fabflow.positioning.registration.register_points`.

Shapes: ``n`` points, leading batch dimensions ``...`` (none for one problem);
metres and the world frame throughout.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import special

from fabflow.positioning.adjustment_tests import (
    MIN_REDUNDANCY,
    POWER,
    TestResult,
    chi2_quantile,
    noncentrality,
)
from fabflow.positioning.rigid_fit import (
    NormalEquations,
    degenerate,
    gauss_newton,
    kabsch,
    kabsch_leave_one_out,
    normal_equations,
    optimize_registration,
    principal_spreads,
)
from fabflow.positioning.small_linalg import (
    eigvalsh3,
    inv3,
    inv_spd6,
    max_eigval_sym2,
    positive_definite3,
)


class PointTestArrays(NamedTuple):
    """The tests of point fits (:func:`point_test_arrays`); ``h = n + 1`` hypotheses.

    Attributes
    ----------
    redundancy
        ``3 n - 6``.
    statistic
        ``(...)`` global test statistic ``v^T Q^-1 v``.
    threshold
        Its critical value (chi-square, ``redundancy`` dof, level ``alpha``).
    p_value
        ``(...)`` its p-value.
    w
        ``(..., h)`` test values: ``sqrt`` of the chi-square(3) statistic of each
        point (its leave-one-out test), then ``|w|`` of the scale hypothesis.
    thresholds
        ``(..., h)`` their critical values (Bonferroni over the ``h`` hypotheses).
    mdb
        ``(..., h)`` minimal detectable biases (metres for points, a number for scale).
    shift
        ``(..., h, 2)`` largest horizontal and vertical base shift of an undetected bias (m).
    bias
        ``(..., n, 3)`` estimated bias of each point (measured minus predicted from the others).
    scale_bias
        ``(...)`` estimated scale error.
    Ninv
        ``(..., 6, 6)`` inverse normal matrix: the pose covariance with absolute weights.
    """

    redundancy: int
    statistic: np.ndarray
    threshold: float
    p_value: np.ndarray
    w: np.ndarray
    thresholds: np.ndarray
    mdb: np.ndarray
    shift: np.ndarray
    bias: np.ndarray
    scale_bias: np.ndarray
    Ninv: np.ndarray


@functools.lru_cache(maxsize=256)
def levels(alpha0: float) -> tuple[np.ndarray, np.ndarray]:
    """Critical ``w`` and ``sqrt(lambda_0)`` for 0-3 degrees of freedom at level ``alpha0``."""
    thr = np.array([math.inf] + [math.sqrt(chi2_quantile(k, alpha0)) for k in (1, 2, 3)])
    lam = np.array([math.inf] + [math.sqrt(noncentrality(alpha0, POWER, k)) for k in (1, 2, 3)])
    return thr, lam


def point_test_arrays(
    eq: NormalEquations, W: np.ndarray, alpha: float, w_max: np.ndarray | None = None
) -> PointTestArrays:
    """Global test, w-tests, MDBs and base shifts of point fits, all points and problems at once.

    The observations are the measured points with covariances ``W^-1``; the
    hypotheses a bias of each point (three columns) and a scale error between
    instrument and robot (column ``R p_i``). Per point ``k``:
    ``S_k = W_k - W_k J_k N^-1 J_k^T W_k`` (the inverse of the covariance of its
    leave-one-out prediction error), ``w_k^2 = b_k^T S_k^-1 b_k`` with
    ``b_k = W_k v_k``, MDB ``sqrt(lambda_0 / lambda_min(S_k))``, and the base
    shift of an undetected bias ``sqrt(lambda_0)`` times the largest singular
    value of ``(N^-1 J_k^T W_k)_xyz S_k^-1/2`` (rows x, y apart from z). Bias
    directions the residuals hardly see (a redundancy number below
    :data:`~fabflow.positioning.adjustment_tests.MIN_REDUNDANCY`) make MDB and shift
    infinite, as in :func:`~fabflow.positioning.adjustment_tests.adjustment_test`,
    whose numbers these are.

    Parameters
    ----------
    eq
        The fit's :class:`~fabflow.positioning.rigid_fit.NormalEquations`.
    W
        ``(..., n, 3, 3)`` information matrices of the measured points (1/m^2).
    alpha
        Level of the global test; the w-tests share it.
    w_max
        ``(..., n)`` largest eigenvalue of each ``W`` when the caller knows it.

    Returns
    -------
    PointTestArrays
    """
    n = eq.q.shape[-2]
    h = n + 1
    r = 3 * n - 6
    thr_table, lam_table = levels(alpha / h)
    Ninv = inv_spd6(eq.N)
    statistic = np.einsum("...ni,...ni->...", eq.v, eq.Wv)
    threshold = chi2_quantile(r, alpha)
    p_value = special.chdtrc(r, statistic)

    # per point: S_k and the base shift map Y_k = (N^-1 J_k^T W_k)[:3]
    X = eq.WJ @ Ninv[..., None, :, :]
    own = 0.5 * (W + np.swapaxes(W, -1, -2))
    S = own - X @ np.swapaxes(eq.WJ, -1, -2)
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    scale = np.maximum(eigvalsh3(own)[..., -1] if w_max is None else w_max, 1e-300)
    ev_min = eigvalsh3(S)[..., 0]
    # every direction seen: lambda_min(S) > MIN_REDUNDANCY lambda_max(W); then also
    # S > MIN_REDUNDANCY W, every redundancy number above it: MDB and shift finite
    full = ev_min > MIN_REDUNDANCY * scale
    all_full = bool(full.all())
    Sinv = inv3(S if all_full else np.where(full[..., None, None], S, np.eye(3)))
    b = eq.Wv
    bias = (Sinv @ b[..., None])[..., 0]
    w = np.sqrt(np.maximum(np.einsum("...i,...i->...", b, bias), 0.0))
    thr = np.full(w.shape, thr_table[3])
    Y = np.swapaxes(X, -1, -2)[..., :3, :]
    T = Y @ Sinv @ np.swapaxes(Y, -1, -2)
    horizontal = max_eigval_sym2(T[..., 0, 0], T[..., 0, 1], T[..., 1, 1])
    spread = np.stack([horizontal, T[..., 2, 2]], -1)
    if all_full:
        mdb = lam_table[3] / np.sqrt(ev_min)
        shift = lam_table[3] * np.sqrt(np.maximum(spread, 0.0))
    else:
        mdb = np.where(full, lam_table[3] / np.sqrt(np.where(full, ev_min, 1.0)), np.inf)
        shift = np.where(full[..., None], lam_table[3] * np.sqrt(np.maximum(spread, 0.0)), np.inf)
        rows = ~full
        w[rows], thr[rows], mdb[rows], shift[rows], bias[rows] = partial_tests(
            S[rows], own[rows], scale[rows], b[rows], Y[rows], thr_table, lam_table
        )

    # scale: one column c = (R p_i) stacked
    Wq = (W @ eq.q[..., None])[..., 0]
    b_s = np.einsum("...ni,...ni->...", Wq, eq.v)
    B_s = np.einsum("...nki,...nk->...i", eq.WJ, eq.q)
    own_s = np.einsum("...ni,...ni->...", eq.q, Wq)
    NB = (Ninv @ B_s[..., None])[..., 0]
    S_s = own_s - np.einsum("...i,...i->...", B_s, NB)
    seen_s = S_s > MIN_REDUNDANCY * np.maximum(own_s, 1e-300)
    visible_s = seen_s & (S_s / own_s >= MIN_REDUNDANCY)
    if np.all(visible_s):
        w_s = np.sqrt(np.maximum(b_s * (1.0 / S_s) * b_s, 0.0))
        bias_s = b_s / S_s
        thr_s = np.full(np.shape(S_s), thr_table[1])
        mdb_s = lam_table[1] / np.sqrt(S_s)
        M_s = NB[..., :3] / np.sqrt(S_s)[..., None]
        shift_s = lam_table[1] * np.stack(
            [np.hypot(M_s[..., 0], M_s[..., 1]), np.abs(M_s[..., 2])], -1
        )
    else:
        S_safe = np.where(seen_s, S_s, 1.0)
        w_s = np.where(seen_s, np.sqrt(np.maximum(b_s * (1.0 / S_safe) * b_s, 0.0)), np.nan)
        bias_s = np.where(seen_s, b_s / S_safe, np.nan)
        thr_s = np.where(seen_s, thr_table[1], np.inf)
        mdb_s = np.where(visible_s, lam_table[1] / np.sqrt(S_safe), np.inf)
        M_s = NB[..., :3] / np.sqrt(S_safe)[..., None]
        shift_s = np.where(
            visible_s[..., None],
            lam_table[1] * np.stack([np.hypot(M_s[..., 0], M_s[..., 1]), np.abs(M_s[..., 2])], -1),
            np.inf,
        )
    return PointTestArrays(
        redundancy=r,
        statistic=statistic,
        threshold=threshold,
        p_value=p_value,
        w=np.concatenate([w, w_s[..., None]], axis=-1),
        thresholds=np.concatenate([thr, np.asarray(thr_s)[..., None]], axis=-1),
        mdb=np.concatenate([mdb, np.asarray(mdb_s)[..., None]], axis=-1),
        shift=np.concatenate([shift, shift_s[..., None, :]], axis=-2),
        bias=bias,
        scale_bias=bias_s,
        Ninv=Ninv,
    )


def partial_tests(
    S: np.ndarray,
    own: np.ndarray,
    scale: np.ndarray,
    b: np.ndarray,
    Y: np.ndarray,
    thr_table: np.ndarray,
    lam_table: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The tests of points whose bias the residuals see only in part (a near-singular ``S_k``).

    Rare (a point that alone fixes a direction: the one point off a line of
    others): their tests use the pseudo-inverse on the directions seen and as
    many degrees of freedom, by eigen-decomposition. ``S``, ``own``, ``Y``
    ``(k, 3, 3)``, ``scale`` ``(k,)``, ``b`` ``(k, 3)`` for ``k`` such points;
    returns their ``w``, thresholds, MDBs, shifts ``(k, 2)`` and biases ``(k, 3)``.
    """
    ev, V = np.linalg.eigh(S)
    seen = ev > MIN_REDUNDANCY * scale[..., None]
    dof = seen.sum(axis=-1)
    inv_ev = np.where(seen, 1.0 / np.where(seen, ev, 1.0), 0.0)
    Sp = (V * inv_ev[..., None, :]) @ np.swapaxes(V, -1, -2)
    bias = (Sp @ b[..., None])[..., 0]
    any_seen = dof > 0
    w = np.where(any_seen, np.sqrt(np.maximum(np.einsum("...i,...i->...", b, bias), 0.0)), np.nan)
    visible = any_seen & positive_definite3(S - MIN_REDUNDANCY * own)
    ev_pos = np.where(visible[..., None], ev, 1.0)
    lam = lam_table[dof]
    mdb = np.where(visible, lam / np.sqrt(ev_pos[..., 0]), np.inf)
    Ms = Y @ ((V / np.sqrt(ev_pos)[..., None, :]) @ np.swapaxes(V, -1, -2))
    horizontal = np.linalg.norm(Ms[..., :2, :], 2, axis=(-2, -1))
    vertical = np.linalg.norm(Ms[..., 2, :], axis=-1)
    shift = np.where(
        visible[..., None], lam[..., None] * np.stack([horizontal, vertical], -1), np.inf
    )
    return w, thr_table[dof], mdb, shift, np.where(any_seen[..., None], bias, np.nan)


class LooTestArrays(NamedTuple):
    """The leave-one-out F-test of point fits with relative weights (:func:`loo_f_test_arrays`).

    Attributes
    ----------
    R, t
        ``(..., 3, 3)`` and ``(..., 3)``: the fit of all the points.
    eq
        Its :class:`~fabflow.positioning.rigid_fit.NormalEquations`.
    Ninv
        ``(..., 6, 6)`` inverse of its normal matrix (relative weights).
    statistics
        ``(..., n)`` F statistic of each point.
    threshold
        Critical value, F(3, 3(n-1)-6) at level ``alpha / n``.
    loo_residuals
        ``(..., n, 3)`` each point measured minus predicted by the fit without it (m).
    """

    R: np.ndarray
    t: np.ndarray
    eq: NormalEquations
    Ninv: np.ndarray
    statistics: np.ndarray
    threshold: float
    loo_residuals: np.ndarray


@functools.lru_cache(maxsize=256)
def f_quantile(dfn: int, dfd: int, level: float) -> float:
    """Upper ``level`` quantile of F(dfn, dfd) (cached: the tests ask for the same few)."""
    return float(special.fdtri(dfn, dfd, 1.0 - level))


def loo_f_test_arrays(
    P: np.ndarray,
    M: np.ndarray,
    omega: np.ndarray,
    alpha: float,
    R: np.ndarray | None = None,
    t: np.ndarray | None = None,
) -> LooTestArrays:
    """Fit of all the points and the leave-one-out F-test of each, relative weights.

    Each point is predicted by the weighted Kabsch fit of the others; the
    prediction error ``d_k`` is normalised by its predicted covariance
    ``omega_k^-1 I + J_k (N - N_k)^-1 J_k^T``, whose inverse is the full fit's
    ``S_k = omega_k I - omega_k^2 J_k N^-1 J_k^T``; the noise level comes from
    the residuals of the fit without the point:
    ``F_k = d_k^T S_k d_k / (3 s_k^2)``, F(3, 3(n-1)-6) distributed.

    Parameters
    ----------
    P, M
        ``(..., n, 3)`` base and measured points (metres), n >= 4.
    omega
        ``(..., n)`` positive weights (1/m^2; their scale cancels).
    alpha
        Level of the test (Bonferroni over the ``n`` points).
    R, t
        The fit of all the points to linearise at, when it is not the weighted
        Kabsch one (the constrained optimizer's); by default that of the stack.
    """
    n = P.shape[-2]
    Rs, ts = kabsch_leave_one_out(P, M, omega)
    if R is None or t is None:
        R, t = Rs[..., 0, :, :], ts[..., 0, :]
    W = omega[..., None, None] * np.eye(3)
    eq = normal_equations(R, t, P, M, W)
    Ninv = inv_spd6(eq.N)
    S = W - eq.WJ @ Ninv[..., None, :, :] @ np.swapaxes(eq.WJ, -1, -2)
    # E[k, i]: point i fitted without point k, minus measured
    E = (P[..., None, :, :] @ np.swapaxes(Rs[..., 1:, :, :], -1, -2)) + ts[..., 1:, None, :]
    E = E - M[..., None, :, :]
    idx = np.arange(n)
    d = -E[..., idx, idx, :]
    stat = np.einsum("...ki,...kij,...kj->...k", d, S, d)
    others = omega[..., None, :] * (1.0 - np.eye(n))
    ssr = np.einsum("...ki,...kic,...kic->...k", others, E, E)
    dof = 3 * (n - 1) - 6
    stat = stat / (3.0 * np.maximum(ssr / dof, 1e-24))
    return LooTestArrays(R, t, eq, Ninv, stat, f_quantile(3, dof, alpha / n), d)


SCALE_HYPOTHESIS = "scale (instrument vs robot)"
"""Label of the scale hypothesis in a registration's tests."""


def as_test_result(arrays: PointTestArrays, labels: Sequence[str]) -> TestResult:
    """The :class:`TestResult` of one problem's point tests (hypotheses: the points, then scale)."""
    n = len(labels)
    r = arrays.redundancy
    statistic = float(arrays.statistic)
    return TestResult(
        redundancy=r,
        statistic=statistic,
        threshold=arrays.threshold,
        p_value=float(arrays.p_value),
        variance_factor=statistic / r,
        labels=(*labels, SCALE_HYPOTHESIS),
        w=arrays.w,
        thresholds=arrays.thresholds,
        mdb=arrays.mdb,
        shift=arrays.shift,
        bias=(*arrays.bias, np.array([float(arrays.scale_bias)])),
        excludable=np.arange(n + 1) < n,
        units=("m",) * n + ("",),
    )


class Fits:
    """The fits of one registration problem on subsets of its points (one, or many at once).

    Parameters
    ----------
    P, M
        ``(n, 3)`` base points (robot base frame) and measured points (world), metres.
    w
        ``(n,)`` weights of the Kabsch fit.
    W
        ``(n, 3, 3)`` information matrices of the measured points (1/m^2).
    w_max
        ``(n,)`` largest eigenvalue of each ``W``.
    method
        ``"closed_form"`` or ``"optimize"`` (SLSQP, one subset at a time).
    refine
        Gauss-Newton on the full ``W`` after Kabsch (with point covariances).
    """

    def __init__(
        self,
        P: np.ndarray,
        M: np.ndarray,
        w: np.ndarray,
        W: np.ndarray,
        w_max: np.ndarray,
        method: str,
        refine: bool,
    ) -> None:
        self.P, self.M, self.w, self.W, self.w_max = P, M, w, W, w_max
        self.method = method
        self.refine = refine

    def one(self, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """The fit of the points in ``keep`` ((n,) bool): ``R``, ``t`` (m), iterations."""
        P, M, w = self.P[keep], self.M[keep], self.w[keep]
        if self.method == "optimize":
            return optimize_registration(P, M, w)
        R, t = kabsch(P, M, w)
        if not self.refine:
            return R, t, 0
        R, t, iters = gauss_newton(R, t, P, M, self.W[keep])
        return R, t, int(iters)

    def many(self, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fits of the point subsets ``sel`` ((m, k) indices), batched: ``(m, 3, 3)``
        rotations, ``(m, 3)`` translations (m), ``(m,)`` iterations."""
        if self.method == "optimize":
            fits = [optimize_registration(self.P[s], self.M[s], self.w[s]) for s in sel]
            R = np.stack([f[0] for f in fits])
            t = np.stack([f[1] for f in fits])
            return R, t, np.array([f[2] for f in fits])
        P, M = self.P[sel], self.M[sel]
        R, t = kabsch(P, M, self.w[sel])
        if not self.refine:
            return R, t, np.zeros(len(sel), dtype=int)
        return gauss_newton(R, t, P, M, self.W[sel])


@dataclass(frozen=True, eq=False)
class Trial:
    """One point left out of a registration, the rest fitted again and tested."""

    index: int
    keep: np.ndarray
    R: np.ndarray
    t: np.ndarray
    iters: int
    passed: bool
    arrays: PointTestArrays
    eq: NormalEquations
    labels: list[str]

    def result(self) -> tuple[TestResult, NormalEquations, np.ndarray]:
        """The tests as a :class:`TestResult`, the fit's normal equations and their inverse."""
        return as_test_result(self.arrays, self.labels), self.eq, self.arrays.Ninv


def leave_each_out(
    fits: Fits, keep: np.ndarray, labels: Sequence[str], alpha: float
) -> list[Trial]:
    """Every point of ``keep`` left out in turn (where the rest spans a plane), all at once."""
    candidates = np.flatnonzero(keep)
    trial_keep = np.repeat(keep[None], len(candidates), axis=0)
    trial_keep[np.arange(len(candidates)), candidates] = False
    sel = np.nonzero(trial_keep)[1].reshape(len(candidates), -1)
    spans = ~degenerate(principal_spreads(fits.P[sel]))
    if not spans.any():
        return []
    sel, candidates, trial_keep = sel[spans], candidates[spans], trial_keep[spans]
    R, t, iters = fits.many(sel)
    W = fits.W[sel]
    eq = normal_equations(R, t, fits.P[sel], fits.M[sel], W)
    arrays = point_test_arrays(eq, W, alpha, fits.w_max[sel])
    passed = tests_passed(arrays)
    return [
        Trial(
            index=int(i),
            keep=trial_keep[j],
            R=R[j],
            t=t[j],
            iters=int(iters[j]),
            passed=bool(passed[j]),
            arrays=PointTestArrays(*(x if np.ndim(x) == 0 else x[j] for x in arrays)),
            eq=NormalEquations(*(x[j] for x in eq)),
            labels=[labels[k] for k in sel[j]],
        )
        for j, i in enumerate(candidates)
    ]


def tests_passed(arrays: PointTestArrays) -> np.ndarray:
    """:attr:`TestResult.passed` of every problem of a batch of point tests."""
    ratio = np.where(np.isfinite(arrays.w), arrays.w / arrays.thresholds, -np.inf)
    k = np.argmax(ratio, axis=-1)[..., None]
    worst_ok = np.take_along_axis(arrays.w, k, -1) <= np.take_along_axis(arrays.thresholds, k, -1)
    return (arrays.statistic <= arrays.threshold) & worst_ok[..., 0]
