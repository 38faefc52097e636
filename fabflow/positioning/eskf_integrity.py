"""Integrity of the UWB/IMU ESKF: does the filter agree with its measurements?

Every range the filter sees has an innovation ``nu`` (measured minus predicted
range) with predicted variance ``S = H P H^T + sigma^2``. Its normalized
innovation squared ``NIS = nu^2 / S`` is chi-square with 1 degree of freedom
when the filter is consistent (its covariance describes its real error), and
the innovations of a consistent Kalman filter are independent, so a sum of
``n`` of them is chi-square with ``n`` degrees of freedom (Bar-Shalom, Li and
Kirubarajan, *Estimation with applications to tracking and navigation*, 2001,
5.4). The gate rejects a range whose NIS exceeds ``gate`` (8.81: 0.3 % of
good ranges).

:func:`consistency` judges the pose at the end of the record. The pose is
returned as the state at the end, and a filter that was disturbed earlier and
recovered is consistent there, so the tests look at the last ``WINDOW_S``
seconds. The filter counts as **diverged** (its pose must not be used) when

1. the gate rejected more than ``MAX_GATED_SHARE`` of the window's ranges: the
   filter no longer believes most of its measurements. A consistent filter
   rejects 0.3 % plus the NLOS ranges; a blocked anchor of four makes 25 %.
   Beyond half, either most lines of sight are blocked or the state is so far
   off that the gate shields it from the ranges that would correct it;
2. fewer than ``MIN_WINDOW_UPDATES`` ranges were accepted in the window: between
   accepted ranges the position covariance only grows (dead reckoning, cubic
   in time), so this is the "covariance growing without bound" case, caught
   where it starts;
3. the accepted ranges of the window disagree with the filter: the sum of their
   NIS exceeds ``chi2_{1-alpha}(n)`` at the integrity level ``alpha`` (0.001).
   The gate truncates the accepted NIS at ``gate``; a truncated chi-square(1)
   is stochastically smaller than an untruncated one (mean 0.971 instead of 1
   at 8.81), so the sum is stochastically smaller than chi-square(n) and the
   test raises a false alarm with probability at most ``alpha``: conservative.
   What it loses in power is the ranges the gate removed, which rule 1 counts;
4. standing still at the end, the gyro reads more than its estimated bias
   (:func:`rest_gyro_test`): with one tag at the IMU the ranges cannot see the
   heading, so a gyro fault would turn the base unseen.

The NIS test has little power against a bias on one anchor that the filter
absorbs into its position: with four anchors the others follow it. So every
anchor also gets Baarda's w-test, run through the filter (:class:`BiasMonitor`),
for a bias starting at the first range and at every ``BIAS_STEP_S`` over the
last ``BIAS_HORIZON_S`` seconds (a step is seen mainly while the filter
absorbs it, so the test needs its onset); their minimal detectable biases
give the protection level. :func:`eskf_integrity` makes the
:class:`~fabflow.positioning.integrity.Integrity` record of all of it. The
whole-run mean NIS is reported alongside (near 1, slightly below because of
the truncation) but does not decide.

What the ranges cannot see is not tested: with one tag at the IMU, roll and
pitch rest on the accelerometer alone, and an accelerometer bias across
gravity tilts the platform unseen (the base moves through ``T_platform_base``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy import special

from fabflow.positioning.adjustment_tests import ALPHA, POWER, TestResult, noncentrality
from fabflow.positioning.integrity import Integrity, record

WINDOW_S = 2.0
"""Length of the window before the pose over which the filter's consistency is tested (s)."""
MAX_GATED_SHARE = 0.5
"""Largest share of the window's ranges the gate may reject before the filter counts as diverged."""
MIN_WINDOW_UPDATES = 10
"""Fewest accepted ranges in the window for the pose to count as measured, not dead-reckoned."""
BIAS_HORIZON_S = 4.0
"""How far before the pose (s) the bias hypotheses start, every ``BIAS_STEP_S``."""
BIAS_STEP_S = 0.25
"""Spacing of the hypothesized bias onsets (s)."""
REST_RADIUS = 0.05
"""How close (m) every estimated position of the last ``REST_WINDOW_S`` must stay to
their mean for the platform to count as standing still: the range-driven position
scatters by 2-4 cm at rest, a platform driving at 0.3 m/s covers 30 cm in a second.
(Not the estimated velocity: a gyro fault makes it scatter too.)"""
REST_WINDOW_S = 1.0
"""How long before the pose the platform must stand still for the gyro test (s)."""


class BiasMonitor:
    """How a constant bias on one anchor's ranges would move the filter, and its w-tests.

    One hypothesis per anchor and onset: from the onset on, every range to that
    anchor is off by ``b``. In the linearized filter the estimate then moves by
    ``s b`` with the sensitivity ``s`` (15,) propagated like the error state:
    ``s <- F s`` per IMU interval and, per applied measurement with gain ``K``,
    ``m = c - H s`` (the innovation's mean per metre of bias; ``c`` = 1 for a
    range of the hypothesis) and ``s <- s + K m``. For a consistent filter the
    innovations ``nu_i`` are independent with variance ``S_i``, so

    ``w = sum(m_i nu_i / S_i) / sqrt(sum(m_i^2 / S_i))``

    is standard normal without the bias: Baarda's w-test run through the filter
    (the Kalman-filter form of the tests in :mod:`fabflow.positioning.integrity`).
    The bias the test finds with probability ``POWER`` is
    ``MDB = sqrt(lambda_0 / sum(m_i^2 / S_i))``, and ``s * MDB`` at the end is
    how far it moves the pose undetected: the protection level. The reset's
    ``G`` (identity up to the attitude correction) is taken as the identity.

    Parameters
    ----------
    n_anchors
        Number of anchors.
    onsets
        Times (s) from which a bias is hypothesized (each anchor gets each onset).
    """

    def __init__(self, n_anchors: int, onsets: np.ndarray) -> None:
        onsets = np.unique(np.asarray(onsets, dtype=float))
        # columns in order of onset: the active ones (onset reached) are a prefix
        self.anchor = np.tile(np.arange(n_anchors), onsets.size)
        self.onset = np.repeat(onsets, n_anchors)
        self.sensitivity = np.zeros((15, self.anchor.size))
        self._wsum = np.zeros(self.anchor.size)
        self._info = np.zeros(self.anchor.size)
        self._n_anchors = n_anchors
        self._active = 0

    def propagate(self, F: np.ndarray) -> None:
        """Carry the sensitivities over one IMU interval with the error-state transition ``F``."""
        k = self._active
        if k:
            self.sensitivity[:, :k] = F @ self.sensitivity[:, :k]

    def correct(
        self,
        H: np.ndarray,
        K: np.ndarray,
        innovation: float,
        S: float,
        anchor: int = -1,
        t: float = -math.inf,
    ) -> None:
        """Account for one applied measurement (``anchor`` -1 for a non-range, e.g. a height)."""
        k = self._active
        while k < self.onset.size and self.onset[k] <= t:
            k += 1
        self._active = k
        if not k:
            return
        sens = self.sensitivity[:, :k]
        m = -(H @ sens)
        if anchor >= 0:
            m[anchor :: self._n_anchors] += 1.0  # the active columns of this anchor
        sens += np.outer(K, m)
        self._wsum[:k] += m * (innovation / S)
        self._info[:k] += m * m / S

    def tests(self, alpha: float = ALPHA) -> BiasTests:
        """The w-tests and MDBs of the hypotheses that saw at least one range."""
        seen = self._info > 0
        h = int(seen.sum())
        alpha0 = alpha / max(h, 1)
        info = self._info[seen]
        return BiasTests(
            anchor=self.anchor[seen],
            onset=self.onset[seen],
            w=self._wsum[seen] / np.sqrt(info),
            threshold=math.sqrt(float(special.chdtri(1, alpha0))),
            mdb=np.sqrt(noncentrality(alpha0, POWER, 1) / info),
            sensitivity=self.sensitivity[:, seen].copy(),
        )


@dataclass(frozen=True)
class BiasTests:
    """The anchor-bias hypotheses of a run (see :class:`BiasMonitor`).

    Attributes
    ----------
    anchor, onset
        (h,) anchor index and onset time (s) of each hypothesis.
    w
        (h,) test values (signed: positive when the ranges look too long).
    threshold
        Critical ``|w|`` (Bonferroni over the ``h`` hypotheses at ``alpha``).
    mdb
        (h,) minimal detectable bias (m).
    sensitivity
        (15, h) change of the final error state per metre of bias.
    """

    anchor: np.ndarray
    onset: np.ndarray
    w: np.ndarray
    threshold: float
    mdb: np.ndarray
    sensitivity: np.ndarray

    @property
    def passed(self) -> bool:
        """Whether every w-test passes."""
        return bool(np.all(np.abs(self.w) <= self.threshold))


def bias_onsets(range_t: np.ndarray, t_end: float) -> np.ndarray:
    """Onsets of the bias hypotheses (s): the first range, then every ``BIAS_STEP_S``
    over the last ``BIAS_HORIZON_S`` before ``t_end``."""
    t0 = float(range_t[0]) if len(range_t) else t_end
    grid = t_end - np.arange(BIAS_STEP_S, BIAS_HORIZON_S + 1e-9, BIAS_STEP_S)
    return np.r_[t0, grid[grid > t0]]


@dataclass(frozen=True)
class RestGyroTest:
    """Whether the gyro reads zero while the platform stands still (see :func:`rest_gyro_test`).

    Attributes
    ----------
    at_rest
        Whether the estimated positions of the last ``REST_WINDOW_S`` stayed
        within ``REST_RADIUS`` of their mean (the test is only made then; it
        passes otherwise).
    residual
        (3,) mean angular rate minus the estimated gyro bias over the window (rad/s, body).
    statistic, threshold
        ``sum(residual^2 / var)`` and its chi-square(3) critical value at ``alpha``.
    """

    at_rest: bool
    residual: np.ndarray
    statistic: float
    threshold: float

    @property
    def passed(self) -> bool:
        """Whether the gyro agrees with a standing platform (or the platform moved)."""
        return not self.at_rest or self.statistic <= self.threshold


def rest_gyro_test(
    imu_t: np.ndarray,
    gyro: np.ndarray,
    p: np.ndarray,
    gyro_bias: np.ndarray,
    P_gyro_bias: np.ndarray,
    gyro_noise: float,
    window_s: float = REST_WINDOW_S,
    alpha: float = ALPHA,
) -> RestGyroTest:
    """Test the gyro against a standing platform over the last ``window_s`` seconds.

    With one tag at the IMU the ranges do not see the heading of a standing
    platform: a gyro bias beyond the filter's model turns the heading (and the
    base, through ``T_platform_base``) unseen. Standing still, the gyro must
    read the estimated bias: the mean rate minus the bias has the variance
    ``P_wb + gyro_noise^2 / T`` per axis (the bias estimate's and the white
    noise's over ``T`` seconds); their normalized sum of squares is chi-square
    with 3 degrees of freedom. The earth's rate (7.3e-5 rad/s) is neglected.

    Parameters
    ----------
    imu_t, gyro
        (M,) times (s) and (M, 3) angular rates (rad/s, body).
    p
        (M, 3) estimated position (m, world).
    gyro_bias, P_gyro_bias
        (3,) estimated gyro bias at the end (rad/s) and its 3x3 covariance.
    gyro_noise
        Gyro white noise density of the filter's model (rad/s/sqrt(Hz)).
    """
    win = imu_t > imu_t[-1] - window_s
    pw = p[win]
    at_rest = bool(np.all(np.linalg.norm(pw - pw.mean(axis=0), axis=1) < REST_RADIUS))
    span = max(float(imu_t[win][-1] - imu_t[win][0]), 1e-3)
    residual = gyro[win].mean(axis=0) - np.asarray(gyro_bias, dtype=float)
    var = np.diag(P_gyro_bias) + gyro_noise**2 / span
    return RestGyroTest(
        at_rest=at_rest,
        residual=residual,
        statistic=float(np.sum(residual**2 / var)),
        threshold=float(special.chdtri(3, alpha)),
    )


@dataclass(frozen=True)
class EskfConsistency:
    """The filter's statistics over a run and its verdict (see the module docstring).

    Attributes
    ----------
    n_updates, n_gated
        Ranges accepted and ranges rejected by the gate over the run.
    nis_mean
        Mean NIS of the accepted ranges over the run (NaN without any).
    window_s
        Length of the test window before the pose (s).
    n_updates_window, n_gated_window
        Ranges accepted and rejected in the window.
    nis_sum_window, nis_mean_window
        Sum and mean NIS of the accepted ranges in the window.
    nis_threshold_window
        The test's critical mean NIS, ``chi2_{1-alpha}(n) / n`` (inf without ranges).
    p_value_window
        Probability of a sum at least this large for a consistent filter.
    gated_share_window
        ``n_gated_window`` over the ranges in the window (NaN without ranges).
    alpha
        Level of the tests.
    diverged
        Whether the filter diverged (rules 1-4 of the module docstring).
    reason
        Why, in one sentence (empty when not diverged).
    bias
        The anchor-bias w-tests (:class:`BiasMonitor`).
    rest
        The gyro test of a standing platform (:func:`rest_gyro_test`), if made.
    """

    n_updates: int
    n_gated: int
    nis_mean: float
    window_s: float
    n_updates_window: int
    n_gated_window: int
    nis_sum_window: float
    nis_mean_window: float
    nis_threshold_window: float
    p_value_window: float
    gated_share_window: float
    alpha: float
    diverged: bool
    reason: str
    bias: BiasTests
    rest: RestGyroTest | None = None

    def checks(self) -> dict[str, Any]:
        """The figures as the ``checks`` of an integrity record."""
        return {
            "n_updates": self.n_updates,
            "n_gated": self.n_gated,
            "nis_mean": self.nis_mean,
            "window_s": self.window_s,
            "n_updates_window": self.n_updates_window,
            "n_gated_window": self.n_gated_window,
            "gated_share_window": self.gated_share_window,
            "max_gated_share": MAX_GATED_SHARE,
            "nis_mean_window": self.nis_mean_window,
            "nis_threshold_window": self.nis_threshold_window,
            "p_value_window": self.p_value_window,
            "diverged": self.diverged,
            "gyro_at_rest": None
            if self.rest is None
            else {
                "at_rest": self.rest.at_rest,
                "residual_rad_s": [float(x) for x in self.rest.residual],
                "statistic": self.rest.statistic,
                "threshold": self.rest.threshold,
            },
        }


def consistency(
    t_end: float,
    range_t: np.ndarray,
    nis: np.ndarray,
    gated: np.ndarray,
    bias: BiasTests,
    rest: RestGyroTest | None = None,
    window_s: float = WINDOW_S,
    alpha: float = ALPHA,
) -> EskfConsistency:
    """Whole-run figures and the window test of the pose at ``t_end`` (module docstring).

    Parameters
    ----------
    t_end
        Time of the pose (s), the end of the window.
    range_t, nis, gated
        (K,) time (s), normalized innovation squared and gate decision of every
        range the filter was offered.
    bias
        The anchor-bias w-tests of the run (``BiasMonitor.tests``).
    rest
        The gyro test of a standing platform (rule 4), if made.
    window_s
        Length of the test window (s).
    alpha
        Level of the chi-square test.
    """
    rt = np.asarray(range_t, dtype=float)
    nis = np.asarray(nis, dtype=float)
    gated = np.asarray(gated, dtype=bool)
    acc = ~gated
    win = rt > t_end - window_s
    acc_win = acc & win
    n_acc, n_gated_w = int(acc_win.sum()), int((gated & win).sum())
    n_win = n_acc + n_gated_w
    s = float(nis[acc_win].sum())
    mean_w = s / n_acc if n_acc else math.nan
    thr = float(special.chdtri(n_acc, alpha)) if n_acc else math.inf
    p = float(special.chdtrc(n_acc, s)) if n_acc else math.nan
    share = n_gated_w / n_win if n_win else math.nan
    where = f"in the last {window_s:g} s before the pose"
    if share > MAX_GATED_SHARE:
        reason = (
            f"the gate rejected {n_gated_w} of {n_win} ranges ({100 * share:.0f} %) {where}: "
            "the filter no longer agrees with its measurements"
        )
    elif n_acc < MIN_WINDOW_UPDATES:
        reason = (
            f"only {n_acc} range(s) accepted {where} (at least {MIN_WINDOW_UPDATES} needed): "
            "the pose rests on dead reckoning"
        )
    elif s > thr:
        reason = (
            f"the ranges {where} disagree with the filter: mean NIS {mean_w:.2f} > "
            f"{thr / n_acc:.2f} (chi-square test, {n_acc} dof, alpha {alpha:g})"
        )
    elif rest is not None and not rest.passed:
        reason = (
            f"standing still, the gyro reads {np.linalg.norm(rest.residual):.2g} rad/s beyond "
            f"its estimated bias (chi-square {rest.statistic:.1f} > {rest.threshold:.1f}): "
            "the heading turns unseen by the ranges"
        )
    else:
        reason = ""
    return EskfConsistency(
        n_updates=int(acc.sum()),
        n_gated=int(gated.sum()),
        nis_mean=float(nis[acc].mean()) if acc.any() else math.nan,
        window_s=float(window_s),
        n_updates_window=n_acc,
        n_gated_window=n_gated_w,
        nis_sum_window=s,
        nis_mean_window=mean_w,
        nis_threshold_window=thr / n_acc if n_acc else math.inf,
        p_value_window=p,
        gated_share_window=share,
        alpha=float(alpha),
        diverged=bool(reason),
        reason=reason,
        bias=bias,
        rest=rest,
    )


def eskf_integrity(
    c: EskfConsistency,
    anchor_ids: Sequence[str] | None = None,
    position_map: np.ndarray | None = None,
    t_end: float | None = None,
) -> Integrity:
    """The integrity record of an ESKF pose: ``"ok"``, or ``"failed"`` with the reason.

    The window's chi-square test goes in ``global_test`` (its variance factor is
    the mean NIS, its redundancy the accepted ranges in the window), the largest
    anchor-bias ``w`` in ``w_test``, their MDBs and the protection level as in
    :func:`fabflow.positioning.integrity.record`; the figures in ``checks``. The
    pose fails when the filter diverged or an anchor-bias w-test fails.

    Parameters
    ----------
    c
        The run's statistics (``EskfTrack.consistency``).
    anchor_ids
        Anchor names for the labels (indices when omitted).
    position_map
        (3, 15) derivative of the reported position by the error state (the body
        position, ``[I 0 0 0 0]``, when omitted; add ``-R [t]x`` on the attitude
        block for a point ``t`` of the body frame).
    t_end
        Time of the pose (s), to label the onsets relative to it.
    """
    b = c.bias
    G = np.eye(3, 15) if position_map is None else np.asarray(position_map, dtype=float)
    t0 = float(b.onset.min()) if b.onset.size else 0.0

    def label(k: int) -> str:
        a = int(b.anchor[k])
        name = anchor_ids[a] if anchor_ids is not None else str(a)
        if b.onset[k] == t0 or t_end is None:
            return f"anchor {name} (since t = {b.onset[k]:.6g} s)"
        return f"anchor {name} (last {t_end - b.onset[k]:.3g} s)"

    n = c.n_updates_window
    test = TestResult(
        redundancy=n,
        statistic=c.nis_sum_window,
        threshold=c.nis_threshold_window * n if n else math.inf,
        p_value=c.p_value_window,
        variance_factor=c.nis_mean_window,
        labels=tuple(label(k) for k in range(b.w.size)),
        w=np.abs(b.w),
        thresholds=np.full(b.w.size, b.threshold),
        mdb=b.mdb,
        shift=_horizontal_vertical((G @ b.sensitivity * b.mdb).T),
        excludable=np.zeros(b.w.size, dtype=bool),
    )
    integrity = record(test, alpha=c.alpha, checks=c.checks())
    if c.diverged:
        reason = c.reason
        if not integrity.w_test["passed"]:  # the anchor-bias tests still say where
            reason += f"; {integrity.reason}"
        integrity = replace(integrity, status="failed", reason=reason)
    return integrity


def _horizontal_vertical(shift: np.ndarray) -> np.ndarray:
    """(h, 3) base shifts as (h, 2): horizontal length and absolute height."""
    return np.column_stack([np.hypot(shift[:, 0], shift[:, 1]), np.abs(shift[:, 2])])
