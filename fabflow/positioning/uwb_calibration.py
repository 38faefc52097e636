"""UWB ranging calibration and range outlier rejection (seeds/003, section 3.3.1).

The calibration fits the measured range ``y`` against the true distance ``x``
per anchor as a line ``y = a + b x`` and corrects measurements with the
inverse ``x = (y - a) / b``. Outlier rejection drops ranges outside physical
bounds and ranges far from the running median of their own series (NLOS
excess delays are positive and short-lived, so a median over a short window
is not pulled by them).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import special

from fabflow.errors import InputError
from fabflow.positioning.medians import nanmedian


@dataclass(frozen=True)
class RangeCalibration:
    """Per-anchor linear range calibration ``y = offset + scale * x``.

    Attributes
    ----------
    offset
        (n_anchors,) ``a`` in metres.
    scale
        (n_anchors,) ``b`` (dimensionless, near 1).
    rms
        (n_anchors,) RMS of the fit residuals (metres); None when not fitted.
    cov
        (n_anchors, 2, 2) covariance of the fitted ``(a, b)``; None when not fitted.
    """

    offset: np.ndarray
    scale: np.ndarray
    rms: np.ndarray | None = None
    cov: np.ndarray | None = None

    @classmethod
    def identity(cls, n_anchors: int) -> RangeCalibration:
        """No correction."""
        return cls(offset=np.zeros(n_anchors), scale=np.ones(n_anchors))

    def take(self, index: np.ndarray) -> RangeCalibration:
        """The calibration of the anchors ``index`` (integer indices), in that order."""
        rms = None if self.rms is None else self.rms[index]
        cov = None if self.cov is None else self.cov[index]
        return RangeCalibration(self.offset[index], self.scale[index], rms, cov)

    @classmethod
    def fit(cls, true_distances: np.ndarray, measured: np.ndarray) -> RangeCalibration:
        """Fit the line per anchor from a calibration campaign.

        Parameters
        ----------
        true_distances
            (k,) true tag-anchor distances (metres), at least two distinct values.
        measured
            (k, samples, n_anchors) or (k, n_anchors) measured ranges (metres); NaN
            marks a missing sample. Each position's samples are reduced to their
            median (robust to stray outliers), then a line is fitted.
        """
        x = np.asarray(true_distances, dtype=float)
        y = np.asarray(measured, dtype=float)
        if y.ndim == 3:
            y = nanmedian(y, 1)
        if y.ndim != 2 or y.shape[0] != x.size:
            raise InputError(
                "calibration data must be (k, n_anchors) or (k, samples, n_anchors) with k "
                f"matching the {x.size} true distances (got {np.shape(measured)})"
            )
        if np.unique(x).size < 2:
            raise InputError("calibration needs at least two distinct true distances")
        offset = np.empty(y.shape[1])
        scale = np.empty(y.shape[1])
        rms = np.empty(y.shape[1])
        cov = np.empty((y.shape[1], 2, 2))
        for j in range(y.shape[1]):
            ok = np.isfinite(y[:, j])
            if np.unique(x[ok]).size < 2:
                raise InputError(f"calibration of anchor {j}: fewer than two distances measured")
            A = np.column_stack([np.ones(ok.sum()), x[ok]])
            (a, b), *_ = np.linalg.lstsq(A, y[ok, j], rcond=None)
            if b <= 0:
                raise InputError(f"calibration of anchor {j}: fitted scale {b:.3f} is not positive")
            offset[j], scale[j] = a, b
            res = y[ok, j] - a - b * x[ok]
            rms[j] = float(np.sqrt(np.mean(res**2)))
            dof = max(int(ok.sum()) - 2, 1)
            cov[j] = float(res @ res) / dof * np.linalg.inv(A.T @ A)
        return cls(offset=offset, scale=scale, rms=rms, cov=cov)

    def bias_sigma(self, distance: np.ndarray | float) -> np.ndarray:
        """Standard deviation (metres) of the range error the fitted line leaves at ``distance``.

        From the fit covariance: ``sqrt([1, d] cov [1, d]^T) / b`` per anchor (last
        axis); zeros when the calibration was not fitted here.
        """
        d = np.asarray(distance, dtype=float)
        if self.cov is None:
            return np.zeros(np.broadcast_shapes(d.shape, self.offset.shape))
        c = self.cov
        var = c[:, 0, 0] + 2 * d * c[:, 0, 1] + d * d * c[:, 1, 1]
        return np.sqrt(np.maximum(var, 0.0)) / self.scale

    def apply(self, ranges: np.ndarray) -> np.ndarray:
        """Corrected ranges ``(y - a) / b``; the last axis indexes anchors."""
        return (np.asarray(ranges, dtype=float) - self.offset) / self.scale

    def apply_indexed(self, ranges: np.ndarray, anchor_index: np.ndarray) -> np.ndarray:
        """Corrected ranges for a flat list of ranges with their anchor indices."""
        idx = np.asarray(anchor_index)
        return (np.asarray(ranges, dtype=float) - self.offset[idx]) / self.scale[idx]

    def to_dict(self, anchor_ids: list[str]) -> dict[str, dict[str, float]]:
        """``{anchor_id: {"offset": a, "scale": b}}``."""
        return {
            k: {"offset": float(a), "scale": float(b)}
            for k, a, b in zip(anchor_ids, self.offset, self.scale, strict=True)
        }

    @classmethod
    def from_mapping(
        cls, data: Mapping[str, Any], anchor_ids: list[str], source: str = "calibration"
    ) -> RangeCalibration:
        """Read ``{anchor_id: {"offset": a, "scale": b}}``; missing anchors are uncorrected."""
        unknown = sorted(set(data) - set(anchor_ids))
        if unknown:
            raise InputError(f"calibration names unknown anchors {unknown}", source)
        cal = cls.identity(len(anchor_ids))
        for j, k in enumerate(anchor_ids):
            if k in data:
                entry = data[k]
                cal.offset[j] = float(entry.get("offset", 0.0))
                cal.scale[j] = float(entry.get("scale", 1.0))
                if cal.scale[j] <= 0:
                    raise InputError(f"calibration of {k}: scale must be positive", source)
        return cal


@dataclass(frozen=True)
class Rejection:
    """Result of :func:`reject_outliers`.

    Attributes
    ----------
    ranges
        The input with rejected ranges set to NaN.
    rejected
        Boolean mask of ranges rejected by this call (not those already NaN).
    out_of_bounds
        Boolean mask of the rejected ranges that were physically impossible.
    """

    ranges: np.ndarray
    rejected: np.ndarray
    out_of_bounds: np.ndarray


def running_median(series: np.ndarray, window: int, causal: bool = False) -> np.ndarray:
    """NaN-aware running median along axis 0.

    Parameters
    ----------
    series
        (N, ...) samples in time order.
    window
        Window length in samples (odd for a centred window).
    causal
        Use only the current and past samples (for online use) instead of a
        centred window.
    """
    x = np.asarray(series, dtype=float)
    window = max(1, int(window))
    if causal:
        pad = [(window - 1, 0)] + [(0, 0)] * (x.ndim - 1)
    else:
        pad = [(window // 2, window - 1 - window // 2)] + [(0, 0)] * (x.ndim - 1)
    padded = np.pad(x, pad, mode="constant", constant_values=np.nan)
    view = sliding_window_view(padded, window, axis=0)
    return nanmedian(view, -1)  # all-NaN windows give NaN


def reject_outliers(
    ranges: np.ndarray,
    sigma: np.ndarray | float,
    window: int = 15,
    k: float = 3.0,
    min_range: float = 0.0,
    max_range: float = 100.0,
    floor: float = 0.1,
    causal: bool = False,
) -> Rejection:
    """Reject physically impossible ranges and ranges far from their running median.

    Parameters
    ----------
    ranges
        (N, ...) calibrated ranges in time order (metres), one series per trailing
        index (anchor, or tag and anchor); NaN for missing.
    sigma
        Range noise standard deviation (metres), scalar or broadcastable to ``ranges``.
    window
        Running median window (samples). Keep it short against the motion: at
        60 Hz and 0.3 m/s, 15 samples span 7.5 cm of travel.
    k
        A range is rejected when ``|range - median| > max(k * sigma, floor)``.
    min_range, max_range
        Physical bounds (metres): below ``min_range`` or beyond ``max_range`` is rejected.
    floor
        Smallest rejection threshold (metres).
    causal
        Use a causal window (online processing).
    """
    y = np.asarray(ranges, dtype=float)
    finite = np.isfinite(y)
    oob = finite & ((y < min_range) | (y > max_range))
    clean = np.where(oob, np.nan, y)
    med = running_median(clean, window, causal=causal)
    thr = np.maximum(k * np.asarray(sigma, dtype=float), floor)
    far = np.isfinite(clean) & (np.abs(clean - med) > thr)
    rejected = oob | far
    return Rejection(ranges=np.where(rejected, np.nan, y), rejected=rejected, out_of_bounds=oob)


def shortest_half_center(series: np.ndarray, fraction: float = 0.25) -> np.ndarray:
    """Robust centre of each series: the median of the densest ``fraction`` of its samples.

    NLOS excess delays are positive and spread over a metre, line-of-sight ranges
    cluster within centimetres: the shortest interval holding a quarter of the
    samples lies inside the line-of-sight cluster even when half of a link's
    ranges are NLOS (where a median is already pulled away).

    Parameters
    ----------
    series
        (N, ...) samples along axis 0 (NaN and infinities ignored).
    fraction
        Share of the finite samples the interval must hold.

    Returns
    -------
    np.ndarray
        (...) centres; NaN for series with fewer than 3 finite samples.
    """
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction must lie in (0, 1], got {fraction}")
    x = np.asarray(series, dtype=float)
    flat = x.reshape(x.shape[0], -1)
    flat = np.where(np.isfinite(flat), flat, np.nan)  # an infinity is no sample either
    n_rows, n_series = flat.shape
    out = np.full(n_series, np.nan)
    n = np.isfinite(flat).sum(axis=0)
    if n_rows < 3 or n_series == 0:
        return out.reshape(x.shape[1:])
    v = np.sort(flat, axis=0)  # NaN last: each column's finite samples first, ascending
    h = np.maximum(2, np.ceil(fraction * n).astype(np.intp))
    first = np.arange(n_rows)[:, None]
    last = np.minimum(first + h - 1, n_rows - 1)
    widths = np.take_along_axis(v, last, axis=0) - v
    widths[first > n - h] = np.inf  # an interval must hold h finite samples
    start = np.argmin(widths, axis=0)  # the first of the shortest, as np.argmin of a column
    cols = np.arange(n_series)
    # the median of v[start : start + h]: its middle sample, or the mean of its middle two
    lo = np.minimum(start + (h - 1) // 2, n_rows - 1)
    hi = np.minimum(start + h // 2, n_rows - 1)
    centre = (v[lo, cols] + v[hi, cols]) / 2
    return np.where(n >= 3, centre, out).reshape(x.shape[1:])


def static_window(sigma: np.ndarray | float, k: float = 3.0, floor: float = 0.1) -> np.ndarray:
    """Half-width (metres) of the window :func:`reject_outliers_static` keeps around a
    link's line-of-sight centre: ``k`` range sigmas, at least ``floor``."""
    return np.maximum(k * np.asarray(sigma, dtype=float), floor)


def _excess_points(excess: tuple[float, float], grid: int) -> np.ndarray:
    """``(grid,)`` midpoints of a uniform NLOS excess's range (metres)."""
    lo, hi = excess
    return lo + (np.arange(grid) + 0.5) / grid * (hi - lo)


CDF_TAIL = 12.0
"""Sigmas beyond the window within which :func:`kept_centre` and :func:`kept_moments`
count an NLOS excess: the normal's tail there, 2e-33, is below the last bit of any
probability or moment they sum it into."""


def _within_reach(points: np.ndarray, edge: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The ascending excess ``points`` (metres) no more than :data:`CDF_TAIL` sigmas ``s``
    beyond the farthest window ``edge``: those beyond add below 1e-32 each to a kept
    share or moment, under the last bit of any sum they are in."""
    reach = np.max(edge + CDF_TAIL * s, initial=-np.inf)
    if not np.isfinite(reach):
        return points
    return points[: np.searchsorted(points, reach, side="right")]


def kept_moments(
    p: np.ndarray | float,
    excess: tuple[float, float],
    sigma: np.ndarray | float,
    lower: np.ndarray | float,
    upper: np.ndarray | float,
    grid: int = 64,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What of a link's ranges :func:`reject_outliers_static` keeps, in expectation.

    A range errs by its Gaussian noise (``sigma``) and, with probability ``p``,
    an NLOS excess ``e`` (uniform over ``excess``, metres); the rejection keeps
    it when its error lies within ``[-lower, upper]`` (metres, about the
    line-of-sight distance). An NLOS range with a small excess is kept now and
    then, and always on the long side: the link's mean is biased long, whatever
    the number of epochs.

    Parameters
    ----------
    p
        Probability that a range of the link carries an NLOS excess.
    excess
        ``(low, high)`` of the uniform excess (metres).
    sigma
        The range noise standard deviation (metres).
    lower, upper
        How far below and above the distance a range is kept (metres).
    grid
        Points of the midpoint rule over the excess.

    Returns
    -------
    kept, first, second, nlos_kept
        Per range, broadcast over the inputs: the probability that it is kept,
        ``E[x 1_kept]`` and ``E[x^2 1_kept]`` of its error ``x`` (metres,
        square metres), and the probability that an NLOS range is kept.
    """
    s = np.asarray(sigma, dtype=float)[..., None]
    upper_edge = np.asarray(upper, dtype=float)[..., None]
    # the points out of reach are left out of the sums, not of their count
    e = np.r_[0.0, _within_reach(_excess_points(excess, grid), upper_edge, s)]
    a = (-np.asarray(lower, dtype=float)[..., None] - e) / s
    b = (upper_edge - e) / s
    pdf_a = np.exp(-0.5 * a * a) / np.sqrt(2.0 * np.pi)
    pdf_b = np.exp(-0.5 * b * b) / np.sqrt(2.0 * np.pi)
    # per excess (0: line of sight): P(kept), E[x 1_kept], E[x^2 1_kept] of x = e + noise
    kept = special.ndtr(b) - special.ndtr(a)
    first = e * kept + s * (pdf_a - pdf_b)
    second = (e * e + s * s) * kept + 2.0 * e * s * (pdf_a - pdf_b)
    second = second + s * s * (a * pdf_a - b * pdf_b)
    p = np.asarray(p, dtype=float)

    def mix(m: np.ndarray) -> np.ndarray:
        return (1.0 - p) * m[..., 0] + p * (m[..., 1:].sum(-1) / grid)

    return mix(kept), mix(first), mix(second), kept[..., 1:].sum(-1) / grid


def _mixture_density(
    x: np.ndarray, p: np.ndarray, excess: tuple[float, float], sigma: np.ndarray
) -> np.ndarray:
    """Density (1/metres) of a range's error ``x``: Gaussian noise, plus with probability
    ``p`` an NLOS excess uniform over ``excess`` (the normal over it in closed form)."""
    lo, hi = excess
    los = np.exp(-0.5 * (x / sigma) ** 2) / (np.sqrt(2.0 * np.pi) * sigma)
    nlos = (special.ndtr((x - lo) / sigma) - special.ndtr((x - hi) / sigma)) / (hi - lo)
    return (1.0 - p) * los + p * nlos


def kept_mean_variance(
    p: np.ndarray | float,
    excess: tuple[float, float],
    sigma: np.ndarray | float,
    lower: np.ndarray | float,
    upper: np.ndarray | float,
    centre: np.ndarray | float,
    slope: np.ndarray | float,
    grid: int = 101,
) -> np.ndarray:
    """``n`` times the variance of a link's corrected mean over ``n`` ranges (square metres).

    The mean of the ranges :func:`reject_outliers_static` keeps, less a bias
    predicted from the share it kept, varies more than the kept ranges alone
    say: the window is centred on the median of the ranges within it, so it
    wanders with the sample and keeps more or fewer NLOS ranges at its long
    edge; and the share kept, which sets the predicted bias, varies with it.
    This is the delta method over the three (their influence functions): the
    mean within the window, the window's centre (the median within it, whose
    spread is set by the density at the centre against that at the edges) and
    the share kept, through the bias's ``slope`` in that share (metres per unit
    share). The parameters are :func:`kept_moments`', with ``centre`` the
    window's expected centre above the line-of-sight distance
    (:func:`kept_centre`; the window is ``[centre - lower, centre + upper]``).
    On simulated links of 300 ranges at 3-12 m, clear or half NLOS, it gives
    the spread of the corrected means to within 5 %, where the kept ranges'
    own spread read 1.7 times too low on a blocked 12 m link.
    """
    p, sigma, lower, upper, centre, slope = (
        np.asarray(a, dtype=float)[..., None] for a in (p, sigma, lower, upper, centre, slope)
    )
    # at least two points per sigma: a window at its 0.1 m floor may be many sigmas wide
    grid = int(np.clip(np.ceil(2.0 * np.max((lower + upper) / sigma, initial=0.0)) + 1, grid, 4001))
    t = np.linspace(0.0, 1.0, grid)
    x = centre - lower + (lower + upper) * t
    w = np.full(grid, 1.0 / (grid - 1))  # the trapezoid rule over the window
    w[[0, -1]] *= 0.5
    w = w * (lower + upper)
    f = _mixture_density(x, p, excess, sigma)
    kept = np.maximum((f * w).sum(-1, keepdims=True), 1e-12)
    mean = (x * f * w).sum(-1, keepdims=True) / kept
    f_c = _mixture_density(centre, p, excess, sigma)
    f_u = _mixture_density(centre + upper, p, excess, sigma)
    f_l = _mixture_density(centre - lower, p, excess, sigma)
    # the median within the window: moving its centre moves the window's edges too
    D = np.maximum(2.0 * f_c - f_u - f_l, 1e-6 * f_c + 1e-12)
    mean_by_centre = ((centre + upper - mean) * f_u - (centre - lower - mean) * f_l) / kept
    side = np.sign(x - centre) / D
    influence = (x - mean) / kept + mean_by_centre * side
    influence = influence - slope * (1.0 - kept + (f_u - f_l) * side)
    # a range left out moves the share kept only
    outside = (slope * kept) ** 2 * np.maximum(1.0 - kept, 0.0)
    value = (influence**2 * f * w).sum(-1) + outside[..., 0]
    # a window that holds none of the density (tens of sigmas off the line-of-sight
    # range, no NLOS share) says nothing of the mean: the noise's variance, not 0
    return np.where(kept[..., 0] > 1e-9, value, sigma[..., 0] ** 2)


def kept_centre(
    p: np.ndarray | float,
    excess: tuple[float, float],
    sigma: np.ndarray | float,
    lower: np.ndarray | float,
    upper: np.ndarray | float,
    steps: int = 2,
    grid: int = 32,
) -> np.ndarray:
    """Where :func:`reject_outliers_static` centres its window, in expectation: the
    median of the ranges within the window, re-centred ``steps`` times from the
    line-of-sight distance (metres above it; the NLOS ranges within the window pull
    it long), to a micrometre. The parameters are :func:`kept_moments`'."""
    s = np.asarray(sigma, dtype=float)[..., None]
    p = np.asarray(p, dtype=float)
    s_los, p_los = s[..., 0], 1.0 - p
    e = _excess_points(excess, grid)

    def cdf(x: np.ndarray) -> np.ndarray:
        # a sum over the excess divided by its points: the mean, without np.mean's overhead
        nlos = special.ndtr((x[..., None] - ahead) / s).sum(-1) / grid
        return p_los * special.ndtr(x / s_los) + p * nlos

    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    centre = np.zeros(np.broadcast_shapes(p.shape, s.shape[:-1], lower.shape, upper.shape))
    for _ in range(steps):
        lo_x, hi_x = centre - lower, centre + upper
        ahead = _within_reach(e, hi_x, s[..., 0])
        half = 0.5 * (cdf(lo_x) + cdf(hi_x))
        for _ in range(20):  # bisection for the median of the kept mixture
            mid = 0.5 * (lo_x + hi_x)
            below = cdf(mid) < half
            lo_x, hi_x = np.where(below, mid, lo_x), np.where(below, hi_x, mid)
        centre = 0.5 * (lo_x + hi_x)
    return centre


def reject_outliers_static(
    ranges: np.ndarray,
    sigma: np.ndarray | float,
    k: float = 3.0,
    min_range: float = 0.0,
    max_range: float = 100.0,
    floor: float = 0.1,
) -> Rejection:
    """Outlier rejection for a standing platform: every series measures one distance.

    Like :func:`reject_outliers`, but the reference of each series is its
    :func:`shortest_half_center` (then the median of the samples within the
    threshold of it) instead of a running median, which stays on the
    line-of-sight distance under heavy NLOS contamination (lines of sight blocked
    by the structure).
    """
    y = np.asarray(ranges, dtype=float)
    finite = np.isfinite(y)
    oob = finite & ((y < min_range) | (y > max_range))
    clean = np.where(oob, np.nan, y)
    thr = static_window(sigma, k, floor)
    center = shortest_half_center(clean)
    # the densest quarter finds the line-of-sight cluster but not its middle: re-centre
    # twice on the samples within the threshold
    for _ in range(2):
        near = np.isfinite(clean) & (np.abs(clean - center[None]) <= thr)
        center = np.where(near.any(axis=0), nanmedian(np.where(near, clean, np.nan), 0), center)
    far = np.isfinite(clean) & (np.abs(clean - center[None]) > thr)
    rejected = oob | far
    return Rejection(ranges=np.where(rejected, np.nan, y), rejected=rejected, out_of_bounds=oob)
