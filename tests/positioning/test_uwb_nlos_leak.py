"""What the static rejection keeps of a link's ranges: the predicted share and moments,
and the link bias the kept NLOS ranges leave, taken off by the station estimate."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy import special

from fabflow.localize.uwb_static import without_nlos_leak
from fabflow.positioning.uwb_calibration import (
    kept_centre,
    kept_mean_variance,
    kept_moments,
    reject_outliers_static,
)
from fabflow.sensors.uwb import UwbErrorModel


@settings(max_examples=25, deadline=None)
@example(p=0.5, sigma=0.125, lower=2.0, upper=4.0, low=0.125, width=0.125, seed=0)
@given(
    p=st.floats(0.01, 1.0),
    sigma=st.floats(0.02, 0.15),
    lower=st.floats(1.5, 4.0),
    upper=st.floats(1.5, 4.0),
    low=st.floats(0.05, 0.6),
    width=st.floats(0.1, 1.5),
    seed=st.integers(0, 2**31),
)
def test_kept_moments_match_a_monte_carlo(p, sigma, lower, upper, low, width, seed) -> None:
    rng = np.random.default_rng(seed)
    n = 400_000
    nlos = rng.random(n) < p
    x = np.where(nlos, rng.uniform(low, low + width, n), 0.0) + sigma * rng.standard_normal(n)
    kept = (x >= -lower * sigma) & (x <= upper * sigma)
    predicted = kept_moments(p, (low, low + width), sigma, lower * sigma, upper * sigma)
    # the last: a probability of the NLOS ranges alone, over those drawn (their number
    # varies about p n; dividing by p n instead made a 7-sigma miss at p = 0.5)
    samples = (kept, kept * x, kept * x * x, kept[nlos].astype(float))
    for k, (value, drawn) in enumerate(zip(predicted, samples, strict=True)):
        if k == 3:  # binomial over the NLOS ranges drawn
            tol = 5 * np.sqrt(value * (1 - value) / max(nlos.sum(), 1)) + 1e-4
        else:
            tol = 5 * drawn.std() / np.sqrt(n) + 1e-6
        assert abs(drawn.mean() - value) <= tol


def _excess(excess, grid):
    """The midpoints of the excess's range the correction integrates over (metres)."""
    return excess[0] + (np.arange(grid) + 0.5) / grid * (excess[1] - excess[0])


def _centre_every_excess(p, excess, sigma, lower, upper, steps=2, grid=32) -> np.ndarray:
    """:func:`kept_centre` written out with every point of the excess in each cumulative
    probability (the tail it leaves out kept in)."""
    s = np.asarray(sigma, dtype=float)[..., None]
    e = _excess(excess, grid)

    def cdf(x):
        nlos = special.ndtr((x[..., None] - e) / s).mean(-1)
        return (1.0 - p) * special.ndtr(x / s[..., 0]) + p * nlos

    centre = np.zeros(np.broadcast_shapes(np.shape(p), s.shape[:-1], np.shape(lower)))
    for _ in range(steps):
        lo_x, hi_x = centre - lower, centre + upper
        half = 0.5 * (cdf(lo_x) + cdf(hi_x))
        for _ in range(20):
            mid = 0.5 * (lo_x + hi_x)
            below = cdf(mid) < half
            lo_x, hi_x = np.where(below, mid, lo_x), np.where(below, hi_x, mid)
        centre = 0.5 * (lo_x + hi_x)
    return centre


def _moments_every_excess(p, excess, sigma, lower, upper, grid=64):
    """:func:`kept_moments` written out over every point of the excess."""
    s = np.asarray(sigma, dtype=float)[..., None]
    e = np.r_[0.0, _excess(excess, grid)]
    a = (-np.asarray(lower, dtype=float)[..., None] - e) / s
    b = (np.asarray(upper, dtype=float)[..., None] - e) / s
    pdf_a, pdf_b = (np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi) for z in (a, b))
    kept = special.ndtr(b) - special.ndtr(a)
    first = e * kept + s * (pdf_a - pdf_b)
    second = (
        (e * e + s * s) * kept + 2.0 * e * s * (pdf_a - pdf_b) + s * s * (a * pdf_a - b * pdf_b)
    )
    p = np.asarray(p, dtype=float)
    mix = [(1.0 - p) * m[..., 0] + p * m[..., 1:].mean(-1) for m in (kept, first, second)]
    return (*mix, kept[..., 1:].mean(-1))


@settings(max_examples=40, deadline=None)
@given(
    p=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=6),
    sigma=st.floats(0.005, 0.5),
    spread=st.floats(0.0, 3.0),
    low=st.floats(0.0, 1.0),
    width=st.floats(0.01, 2.0),
    half_width=st.floats(0.01, 0.8),
)
def test_the_nlos_correction_leaves_out_only_what_no_bit_holds(
    p, sigma, spread, low, width, half_width
) -> None:
    # links of different sigmas in one call: the tail left out of the window centre
    # and of the kept share and moments is set by the widest
    p = np.asarray(p)
    s = sigma * (1.0 + spread * np.linspace(0.0, 1.0, len(p)))
    excess = (low, low + width)
    window = np.maximum(half_width, 3.0 * s)
    centre = kept_centre(p, excess, s, window, window)
    assert np.all(np.isfinite(centre))
    assert np.allclose(
        centre, _centre_every_excess(p, excess, s, window, window), atol=1e-9, rtol=0
    )
    got = kept_moments(p, excess, s, window, window)
    want = _moments_every_excess(p, excess, s, window, window)
    for g, w in zip(got, want, strict=True):
        assert np.all(np.isfinite(g))
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-30)


def _links(p: float, d: float, seed: int, links: int = 400) -> tuple:
    """``links`` simulated links of 300 epochs at ``d`` metres, a share ``p`` of their
    ranges NLOS: the ranges, those the rejection keeps, and the corrected ones. The
    noise is a noisy chip's (5 cm, growing 1 cm/m): from 6 m its cleaning window
    reaches into the NLOS excess (with the default 3.3 cm it does not)."""
    model = UwbErrorModel(sigma_1m=0.05, growth=0.01)
    rng = np.random.default_rng(seed)
    sigma = float(model.sigma(d))
    nlos = rng.random((300, 1, links)) < p
    excess = np.where(nlos, rng.uniform(*model.nlos_excess, nlos.shape), 0.0)
    y = d + sigma * rng.standard_normal(nlos.shape) + excess
    kept = reject_outliers_static(y, model.sigma(y)).ranges
    corrected, link_sigma = without_nlos_leak(model, y, kept, lambda r: 0.0 * r)
    n_kept = np.isfinite(kept).sum(axis=0)
    return sigma, kept, corrected, link_sigma, n_kept


@pytest.mark.parametrize("d", [3.0, 6.0, 9.0, 12.0])
@pytest.mark.parametrize("p", [0.5, 0.02])
def test_the_estimate_takes_off_the_bias_kept_nlos_ranges_leave(p: float, d: float) -> None:
    """A blocked line of sight (half the ranges NLOS) or a clear one (2 %), 3-12 m: the
    kept ranges' mean is long, by up to five of its sigmas on a blocked 12 m link;
    corrected, by at most three tenths of one. The NLOS share comes from the share the
    rejection left out, not from knowing which links are blocked."""
    sigma, kept, corrected, _, n_kept = _links(p, d, seed=int(10 * d + 100 * p))
    mean_sigma = sigma / np.sqrt(n_kept.mean())
    before = np.nanmean(kept, axis=0) - d
    after = np.nanmean(corrected, axis=0) - d
    if p == 0.5 and d >= 6.0:
        assert before.mean() > mean_sigma
    assert abs(after.mean()) < 0.3 * mean_sigma


@pytest.mark.parametrize("d", [3.0, 6.0, 9.0, 12.0])
@pytest.mark.parametrize("p", [0.5, 0.02])
def test_the_corrected_means_spread_as_predicted(p: float, d: float) -> None:
    """The corrected means scatter as predicted, clear or blocked, 3-12 m: with the
    window's wander and the estimated share's in the variance (the kept ranges' own
    spread alone read 1.4 times too low on a blocked 9 m link, 1.7 on a 12 m one)."""
    sigma, _, corrected, link_sigma, n_kept = _links(p, d, seed=7)
    after = np.nanmean(corrected, axis=0) - d
    predicted = np.sqrt(np.mean(sigma**2 / n_kept + link_sigma**2))
    # 400 links: the ratio of standard deviations is known to about 3.5 %
    assert 0.88 < after.std() / predicted < 1.12


def test_ranges_the_model_does_not_explain_do_not_count_as_nlos() -> None:
    """A measured link that loses ranges to spikes metres long and to dropouts (zeros):
    the cleaning rejects them, and they are no NLOS share, so the correction leaves the
    link as it would without them, instead of pulling it short."""
    model = UwbErrorModel()
    d = 10.0
    rng = np.random.default_rng(3)
    y = d + float(model.sigma(d)) * rng.standard_normal((300, 1, 1))
    clean = without_nlos_leak(model, y, reject_outliers_static(y, model.sigma(y)).ranges, 0.0)
    spiked = y.copy()
    spiked[:150] = rng.uniform(2.0, 50.0, (150, 1, 1)) + d  # half the ranges far off
    spiked[150:180] = 0.0  # dropouts
    kept = reject_outliers_static(spiked, model.sigma(spiked)).ranges
    assert np.isfinite(kept).sum() <= 120
    corrected, link_sigma = without_nlos_leak(model, spiked, kept, 0.0)
    assert abs(np.nanmean(corrected) - np.nanmean(kept)) < 0.002  # as on the clean link
    assert abs(np.nanmean(clean[0]) - np.nanmean(y)) < 0.002
    assert link_sigma.max() < 0.01


@settings(max_examples=60, deadline=None)
@example(p=0.0, sigma=0.01171875, lower=1.0, upper=1.0, centre=0.0, slope=0.0)
@example(p=0.5, sigma=0.0001, lower=0.1, upper=0.1, centre=0.0, slope=1.0)
# a window 40 sigmas above a clear link's density: none of it is kept
@example(p=0.0, sigma=0.00390625, lower=0.125, upper=1.0, centre=0.28125, slope=0.0)
@given(
    p=st.floats(0.0, 1.0),
    sigma=st.floats(0.001, 0.3),
    lower=st.floats(0.1, 1.0),
    upper=st.floats(0.1, 1.0),
    centre=st.floats(-0.05, 0.3),
    slope=st.floats(-2.0, 2.0),
)
def test_the_corrected_mean_variance_is_finite_and_positive(
    p, sigma, lower, upper, centre, slope
) -> None:
    # whatever the share (all NLOS: a flat density, a median hardly pinned) and window
    # (one many sigmas wide, as the 0.1 m floor makes it for a fine ranging noise)
    value = kept_mean_variance(p, (0.3, 1.5), sigma, lower, upper, centre, slope)
    assert np.isfinite(value) and value > 0.0
    if p == 0.0 and slope == 0.0 and centre == 0.0 and min(lower, upper) > 5 * sigma:
        # a plain normal, all of it kept: the mean's variance is the noise's
        assert value == pytest.approx(sigma**2, rel=0.05)
