"""Quality control of a least-squares pose: the tests a surveyor runs before trusting it.

Every pose fabflow estimates is the solution of a (linearized) Gauss-Markov
model ``l = A x + v`` with observation covariance ``Q``: ranges, measured prism
points, point-to-plane distances. With redundancy ``r = m - u`` the residuals
``v`` carry the information to test it (Baarda's data snooping, as in any
geodetic adjustment text; Teunissen, *Testing theory*, 2000):

- **Global test** of the variance factor: ``T = v^T Q^-1 v`` is chi-square with
  ``r`` degrees of freedom when the model and ``Q`` are right; it fails at level
  ``alpha`` when ``T > chi2_{1-alpha}(r)``.
- **w-test** per hypothesis (one observation, one anchor's ranges, one prism
  point, a scale error): for a bias ``nabla`` entering as ``l = A x + c nabla``,
  ``w = c^T Q^-1 v / sqrt(c^T Q^-1 Q_vv Q^-1 c)`` is standard normal without the
  bias (``Q_vv = Q - A N^-1 A^T``, ``N = A^T Q^-1 A``). A hypothesis of ``k``
  columns (a 3D point) has the chi-square(k) statistic
  ``T_c = b^T S^-1 b`` with ``b = C^T Q^-1 v``, ``S = C^T Q^-1 Q_vv Q^-1 C``. The
  levels are Bonferroni-corrected over the hypotheses tested, so that the
  w-tests together raise a false alarm with probability at most ``alpha``; with
  the global test a clean solution fails with probability at most ``2 alpha``.
- **Internal reliability**: the minimal detectable bias (MDB) of a hypothesis,
  the largest bias the w-test may miss (it finds every bias on the ellipsoid
  ``nabla^T S nabla = lambda_0`` with probability ``POWER``):
  ``|nabla| = sqrt(lambda_0 / lambda_min(S))``. A direction of the bias that
  the redundancy cannot see at all (redundancy number ``mu`` of
  ``S x = mu C^T Q^-1 C x`` below ``MIN_REDUNDANCY``, e.g. one of three prism
  points moved normal to their plane) makes the MDB infinite.
- **External reliability**: a bias moves the estimate by
  ``dx = N^-1 A^T Q^-1 C nabla``; mapped to the base position (``M = G N^-1
  A^T Q^-1 C``), the largest horizontal and vertical shift over the ellipsoid
  of undetected biases is ``sqrt(lambda_0) |M S^-1/2|`` (spectral norm, rows of
  ``M`` for the plane and the height apart). Its largest value over all
  hypotheses is the **protection level**: a single fault the tests miss with
  probability above ``1 - POWER`` moves the base by at most that much; it is
  infinite when any hypothesis has an undetectable direction.

:func:`adjustment_test` computes all of it for one solution, and
:func:`one_column_tests_many` for many solutions of one shape at once (a
simulated run's visits); :func:`~fabflow.positioning.integrity.identify` picks
the observation to exclude, and :mod:`fabflow.positioning.integrity` records
the outcome.

``Q`` is given as a :class:`Covariance`: block-diagonal (prism points) or
diagonal plus a low-rank part (ranges sharing an anchor's calibration error),
so that thousands of ranges are tested in linear time.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, special

from fabflow.positioning.observation_covariance import Covariance

ALPHA = 1e-3
"""Default significance level of the tests (false alarm probability of one solve)."""
POWER = 0.8
"""Probability with which the tests find a bias of the minimal detectable size."""
MIN_REDUNDANCY = 1e-9
"""Redundancy number below which a bias direction counts as undetectable."""


@dataclass(frozen=True)
class Hypothesis:
    """An alternative to the model: a bias entering the observations as ``C nabla``.

    Attributes
    ----------
    label
        What is suspected, in the user's words (``"anchor A3"``, ``"prism P2"``).
    columns
        (m, k) how a bias of each of its ``k`` components changes the observations.
    excludable
        Whether the observations it names can be left out and the pose solved
        again (a scale error cannot).
    unit
        Unit of the bias (``"m"``, or ``""`` for a pure number such as a scale).
    """

    label: str
    columns: np.ndarray
    excludable: bool = True
    unit: str = "m"


@dataclass(frozen=True)
class TestResult:
    """The tests of one solution (see the module docstring).

    Attributes
    ----------
    redundancy
        Degrees of freedom ``r = m - u``.
    statistic, threshold, p_value
        Global test: ``v^T Q^-1 v``, its critical value and p-value.
    variance_factor
        ``statistic / redundancy`` (about 1 when ``Q`` is right).
    labels
        The hypotheses tested.
    w
        (h,) their test values: ``|w|`` for one-column hypotheses, ``sqrt(T_c)``
        for more columns (so every value compares with ``thresholds`` alike).
    thresholds
        (h,) critical values of ``w`` (Bonferroni over the hypotheses).
    mdb
        (h,) minimal detectable bias of each hypothesis (its units: metres for
        ranges and points, a pure number for scale); infinite when a direction
        of the bias is undetectable.
    shift
        (h, 2) largest horizontal and vertical base shift (metres) an undetected
        bias of each hypothesis can cause (infinite when undetectable).
    bias
        Per hypothesis, the estimated bias ``S^-1 b`` (its ``k`` components): for
        one observation or point, what it would read had it been left out
        (measured minus predicted from the others).
    excludable
        (h,) whether each hypothesis names observations that can be left out.
    """

    redundancy: int
    statistic: float
    threshold: float
    p_value: float
    variance_factor: float
    labels: tuple[str, ...]
    w: np.ndarray
    thresholds: np.ndarray
    mdb: np.ndarray
    shift: np.ndarray
    bias: tuple[np.ndarray, ...] = ()
    excludable: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    units: tuple[str, ...] = ()

    @property
    def global_passed(self) -> bool:
        """Whether the global test passes (no redundancy: nothing to test, passes)."""
        return global_passes(self.redundancy, self.statistic, self.threshold)

    @property
    def worst(self) -> int | None:
        """Index of the hypothesis with the largest ``w / threshold``, or None."""
        if len(self.w) == 0:
            return None
        ratio = np.where(np.isfinite(self.w), self.w / self.thresholds, -np.inf)
        return int(np.argmax(ratio))

    @property
    def passed(self) -> bool:
        """Global test and every w-test pass."""
        k = self.worst
        return self.global_passed and (k is None or self.w[k] <= self.thresholds[k])

    def protection_level(self) -> tuple[float, float]:
        """Largest horizontal and vertical base shift of an undetected bias (metres).

        Infinite when any hypothesis has a direction the tests cannot see, or
        when there is no redundancy to test with.
        """
        if self.redundancy <= 0:
            return math.inf, math.inf
        if len(self.shift) == 0:
            return 0.0, 0.0
        s = np.where(np.isnan(self.shift), math.inf, np.asarray(self.shift, dtype=float))
        return float(s[:, 0].max()), float(s[:, 1].max())


@functools.lru_cache(maxsize=1024)
def chi2_quantile(dof: int, alpha: float) -> float:
    """Critical value of a chi-square(dof) test at level ``alpha`` (cached per dof and level)."""
    return float(special.chdtri(dof, alpha))


@functools.lru_cache(maxsize=256)
def noncentrality(alpha0: float, power: float = POWER, dof: int = 1) -> float:
    """Non-centrality ``lambda_0`` at which a chi-square(dof) test at ``alpha0`` has ``power``.

    For one degree of freedom this is ``(z_{1-alpha0/2} + z_{power})^2``, Baarda's
    ``lambda_0`` (17.07 for ``alpha0 = 0.001``, ``power = 0.8``).
    """
    crit = chi2_quantile(dof, alpha0)

    def gap(lam: float) -> float:
        return float(special.chndtr(crit, dof, lam)) - (1.0 - power)

    hi = 1.0
    while gap(hi) > 0:
        hi *= 2.0
    return float(optimize.brentq(gap, 0.0, hi, xtol=1e-10))


def global_passes(redundancy: int, statistic: float, threshold: float) -> bool:
    """Whether a global test passes (no redundancy: nothing to test, passes)."""
    return redundancy <= 0 or statistic <= threshold


def global_test(
    A: np.ndarray,
    Q: Covariance,
    v: np.ndarray,
    alpha: float = ALPHA,
    extra_statistic: float = 0.0,
    extra_redundancy: int = 0,
) -> tuple[int, float, float]:
    """The global test of :func:`adjustment_test` alone: redundancy, statistic
    ``v^T Q^-1 v`` (plus ``extra_statistic``) and critical value at ``alpha``
    (``inf`` without redundancy). For a caller that needs no w-test."""
    A = np.asarray(A, dtype=float)
    v = np.asarray(v, dtype=float)
    r, statistic = _global(A, Q, v, extra_statistic, extra_redundancy)
    return int(r), float(statistic), float(_thresholds(r, alpha))


def _global(
    A: np.ndarray, Q: Covariance, v: np.ndarray, extra_statistic: float, extra_redundancy: int
) -> tuple[np.ndarray, np.ndarray]:
    """Redundancy and statistic of the global test of ``A`` (..., m, u) and ``v`` (..., m)."""
    r = A.shape[-2] - np.linalg.matrix_rank(A) + extra_redundancy
    statistic = np.einsum("...m,...m->...", v, Q.solve(v)) + extra_statistic
    return np.asarray(r), np.asarray(statistic)


def _thresholds(r: np.ndarray, alpha: float) -> np.ndarray:
    """Critical value of the global test of each redundancy ``r`` (``inf`` at none)."""
    values, index = np.unique(r, return_inverse=True)
    each = np.array([chi2_quantile(int(x), alpha) if x > 0 else math.inf for x in values])
    return each[index.reshape(np.shape(r))]


def adjustment_test(
    A: np.ndarray,
    Q: Covariance,
    v: np.ndarray,
    hypotheses: Sequence[Hypothesis],
    alpha: float = ALPHA,
    position_map: np.ndarray | None = None,
    prior_information: np.ndarray | None = None,
    extra_statistic: float = 0.0,
    extra_redundancy: int = 0,
) -> TestResult:
    """Global test, w-tests, MDBs and external reliability of one least-squares solution.

    Parameters
    ----------
    A
        (m, u) design matrix: derivative of the observations by the parameters at
        the solution.
    Q
        Observation covariance (m observations).
    v
        (m,) residuals, observed minus computed at the solution.
    hypotheses
        The alternatives to test.
    alpha
        Level of the global test; the w-tests share it (Bonferroni).
    position_map
        (3, u) derivative of the base position by the parameters (identity on the
        first three parameters when ``None``).
    prior_information
        (u, u) information of prior knowledge of the parameters (a heading prior),
        added to ``N``; it is not an observation and adds no redundancy.
    extra_statistic, extra_redundancy
        A part of ``v^T Q^-1 v`` solved apart, and its degrees of freedom, added to
        the global test: the scatter of repeated observations about the means that
        ``A`` and ``v`` hold (every hypothesis must be constant over each group).
    """
    A = np.asarray(A, dtype=float)
    v = np.asarray(v, dtype=float)
    m = A.shape[0]
    columns = [np.asarray(hyp.columns, dtype=float).reshape(m, -1) for hyp in hypotheses]
    if columns and all(C.shape[1] == 1 for C in columns):
        return one_column_test(
            A, Q, v, [hyp.label for hyp in hypotheses], np.concatenate(columns, axis=1), alpha,
            position_map, prior_information, extra_statistic, extra_redundancy,
            excludable=[hyp.excludable for hyp in hypotheses],
            units=[hyp.unit for hyp in hypotheses],
        )  # fmt: skip
    QiA, Ninv, r_, statistic_, p_, G = _solution(
        A, Q, v, position_map, prior_information, extra_statistic, extra_redundancy
    )
    r, statistic, p_value = int(r_), float(statistic_), float(p_)
    threshold = float(_thresholds(r_, alpha))
    h = len(hypotheses)
    w = np.full(h, np.nan)
    thr = np.full(h, np.inf)
    mdb = np.full(h, np.inf)
    shift = np.full((h, 2), np.inf)
    bias = [np.full(C.shape[1], np.nan) for C in columns]
    if h and r > 0:
        alpha0 = alpha / h
        for i, C in enumerate(columns):
            QiC = Q.solve(C)
            b = QiC.T @ v
            B = QiA.T @ C
            own = 0.5 * (C.T @ QiC + (C.T @ QiC).T)
            S = own - B.T @ Ninv @ B
            S = 0.5 * (S + S.T)
            ev, V = np.linalg.eigh(S)
            scale = max(float(np.linalg.eigvalsh(own)[-1]), 1e-300)
            seen = ev > MIN_REDUNDANCY * scale
            if not seen.any():
                continue
            Sinv = (V[:, seen] / ev[seen]) @ V[:, seen].T
            bias[i] = Sinv @ b
            w[i] = math.sqrt(max(float(b @ Sinv @ b), 0.0))
            dof = int(seen.sum())
            thr[i] = math.sqrt(chi2_quantile(dof, alpha0))
            if _redundancy_numbers(own, S).min() < MIN_REDUNDANCY:
                continue  # a direction of this bias is invisible: MDB and shift infinite
            lam = noncentrality(alpha0, POWER, dof)
            mdb[i] = math.sqrt(lam / ev[0])
            # base shift per unit bias, then its largest value over nabla^T S nabla = lam
            M = (G @ Ninv @ B) @ ((V / np.sqrt(ev)) @ V.T)
            shift[i] = math.sqrt(lam) * np.array([np.linalg.norm(M[:2], 2), np.linalg.norm(M[2])])
    return TestResult(
        redundancy=r,
        statistic=statistic,
        threshold=threshold,
        p_value=p_value,
        variance_factor=statistic / r if r > 0 else math.nan,
        labels=tuple(hyp.label for hyp in hypotheses),
        w=w,
        thresholds=thr,
        mdb=mdb,
        shift=shift,
        bias=tuple(bias),
        excludable=np.array([hyp.excludable for hyp in hypotheses], dtype=bool),
        units=tuple(hyp.unit for hyp in hypotheses),
    )


def one_column_test(
    A: np.ndarray,
    Q: Covariance,
    v: np.ndarray,
    labels: Sequence[str],
    C: np.ndarray,
    alpha: float = ALPHA,
    position_map: np.ndarray | None = None,
    prior_information: np.ndarray | None = None,
    extra_statistic: float = 0.0,
    extra_redundancy: int = 0,
    excludable: Sequence[bool] | None = None,
    units: Sequence[str] | None = None,
) -> TestResult:
    """:func:`adjustment_test` where every hypothesis is one column, given as the
    columns ``C`` ((m, h), one per label) instead of :class:`Hypothesis` objects:
    without making an object per hypothesis. ``excludable`` and ``units`` default
    to :class:`Hypothesis`' defaults; the other parameters are :func:`adjustment_test`'s.
    """
    A = np.asarray(A, dtype=float)
    v = np.asarray(v, dtype=float)
    return _one_column_results(
        A, Q, v, labels, np.asarray(C, dtype=float), alpha, position_map, prior_information,
        extra_statistic, extra_redundancy, excludable, units, batched=False,
    )[0]  # fmt: skip


def one_column_tests_many(
    A: np.ndarray,
    Q: Covariance,
    v: np.ndarray,
    labels: Sequence[str],
    C: np.ndarray,
    alpha: float = ALPHA,
    position_map: np.ndarray | None = None,
    prior_information: np.ndarray | None = None,
) -> list[TestResult]:
    """:func:`one_column_test` of many solutions of one shape at once: ``A``
    (V, m, u), ``v`` (V, m), ``Q`` a stack of V diagonal-plus-low-rank covariances
    (:meth:`Covariance.solve`), the same hypotheses (``labels``, ``C`` (m, h) or
    (V, m, h)) and ``position_map`` (3, u) or (V, 3, u). A simulated run's visits
    test their platform fixes in one call instead of one per visit.
    """
    A = np.asarray(A, dtype=float)
    v = np.asarray(v, dtype=float)
    return _one_column_results(
        A, Q, v, labels, np.asarray(C, dtype=float), alpha, position_map, prior_information,
        0.0, 0, None, None, batched=True,
    )  # fmt: skip


def _one_column_results(
    A: np.ndarray,
    Q: Covariance,
    v: np.ndarray,
    labels: Sequence[str],
    C: np.ndarray,
    alpha: float,
    position_map: np.ndarray | None,
    prior_information: np.ndarray | None,
    extra_statistic: float,
    extra_redundancy: int,
    excludable: Sequence[bool] | None,
    units: Sequence[str] | None,
    batched: bool,
) -> list[TestResult]:
    """The tests of one solution (``batched`` False) or of a stack of them, as records."""
    QiA, Ninv, r, statistic, p_value, G = _solution(
        A, Q, v, position_map, prior_information, extra_statistic, extra_redundancy
    )
    h = len(labels)
    if h:
        C = np.broadcast_to(C, (*A.shape[:-1], h))  # the same hypotheses for every solution
        w, thr, mdb, shift, bias = _one_column_tests(C, Q, QiA, Ninv, v, G, alpha / h)
    else:
        w = thr = mdb = bias = np.zeros((*r.shape, 0))
        shift = np.zeros((*r.shape, 0, 2))
    if not batched:  # one solution: a stack of one
        r, statistic, p_value = r[None], statistic[None], p_value[None]
        w, thr, mdb, shift, bias = w[None], thr[None], mdb[None], shift[None], bias[None]
    # without redundancy nothing is tested
    tested = (r > 0)[:, None]
    w = np.where(tested, w, np.nan)
    thr, mdb = np.where(tested, thr, np.inf), np.where(tested, mdb, np.inf)
    shift, bias = np.where(tested[..., None], shift, np.inf), np.where(tested, bias, np.nan)
    threshold = _thresholds(r, alpha)
    names = tuple(labels)
    flags = np.ones(h, dtype=bool) if excludable is None else np.array(excludable, dtype=bool)
    unit = ("m",) * h if units is None else tuple(units)
    return [
        TestResult(
            redundancy=int(r[i]),
            statistic=float(statistic[i]),
            threshold=float(threshold[i]),
            p_value=float(p_value[i]),
            variance_factor=float(statistic[i] / r[i]) if r[i] > 0 else math.nan,
            labels=names,
            w=w[i],
            thresholds=thr[i],
            mdb=mdb[i],
            shift=shift[i],
            bias=tuple(bias[i][:, None]),
            excludable=flags.reshape(h),
            units=unit,
        )
        for i in range(len(r))
    ]


def _solution(
    A: np.ndarray,
    Q: Covariance,
    v: np.ndarray,
    position_map: np.ndarray | None,
    prior_information: np.ndarray | None,
    extra_statistic: float,
    extra_redundancy: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What every test of :func:`adjustment_test` builds on, over any leading dimensions
    of ``A`` (..., m, u) and ``v`` (..., m): ``Q^-1 A``, the inverse normal matrix,
    the redundancy, statistic and p-value of the global test, and the position map."""
    QiA = Q.solve(A)
    N = np.swapaxes(A, -1, -2) @ QiA
    if prior_information is not None:
        N = N + prior_information
    Ninv = np.linalg.pinv(N)
    r, statistic = _global(A, Q, v, extra_statistic, extra_redundancy)
    p_value = np.where(r > 0, special.chdtrc(np.maximum(r, 1), statistic), 1.0)
    u = A.shape[-1]
    G = np.eye(3, u) if position_map is None else np.asarray(position_map, dtype=float)
    return QiA, Ninv, r, statistic, p_value, G


def _one_column_tests(
    C: np.ndarray,
    Q: Covariance,
    QiA: np.ndarray,
    Ninv: np.ndarray,
    v: np.ndarray,
    G: np.ndarray,
    alpha0: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The w-tests, MDBs and shifts of :func:`adjustment_test` for one-column hypotheses.

    The same formulas as its loop with every matrix ``S`` a number, for all
    hypotheses at once (``C``: (..., m, h), one column each), so that a platform
    with many anchors and links (hundreds of hypotheses, every one refitted when a
    fault is searched for) costs one solve with ``Q`` instead of one per
    hypothesis; over any leading dimensions (many solutions). Returns ``w,
    thresholds, mdb, shift`` as :class:`TestResult` holds them and ``bias``
    (..., h), each hypothesis' one component.
    """
    QiC = Q.solve(C)
    b = np.einsum("...mh,...m->...h", QiC, v)
    B = np.swapaxes(QiA, -1, -2) @ C
    own = np.einsum("...ij,...ij->...j", C, QiC)
    S = own - np.einsum("...ih,...ij,...jh->...h", B, Ninv, B)
    seen = S > MIN_REDUNDANCY * np.maximum(own, 1e-300)
    Ss = np.where(seen, S, 1.0)
    w = np.where(seen, np.abs(b) / np.sqrt(Ss), np.nan)
    bias = np.where(seen, b / Ss, np.nan)
    thr = np.where(seen, math.sqrt(chi2_quantile(1, alpha0)), np.inf)
    visible = seen & (S / np.maximum(own, 1e-300) >= MIN_REDUNDANCY)
    lam = noncentrality(alpha0, POWER, 1)
    mdb = np.where(visible, np.sqrt(lam / Ss), np.inf)
    # (..., 3, h): base shift per unit of the scaled bias
    M = (G @ Ninv @ B) / np.sqrt(Ss)[..., None, :]
    plane, height = np.linalg.norm(M[..., :2, :], axis=-2), np.abs(M[..., 2, :])
    shift = np.where(visible[..., None], math.sqrt(lam) * np.stack([plane, height], -1), np.inf)
    return w, thr, mdb, shift, bias


def _redundancy_numbers(own: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Eigenvalues ``mu`` of ``S x = mu own x``: the share of a bias the residuals see."""
    d, E = np.linalg.eigh(own)
    keep = d > 1e-300
    W = E[:, keep] / np.sqrt(d[keep])
    return np.linalg.eigvalsh(W.T @ S @ W)
