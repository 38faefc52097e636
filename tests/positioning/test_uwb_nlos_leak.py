"""What the static rejection keeps of a link's ranges: the predicted share and moments,
and the link bias the kept NLOS ranges leave, taken off by the station estimate."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.localize.uwb import _without_nlos_leak
from fabflow.positioning.uwb_calibration import kept_moments, reject_outliers_static
from fabflow.sensors.uwb import UwbErrorModel


@settings(max_examples=25, deadline=None)
@given(
    p=st.floats(0.0, 1.0),
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
    samples = (kept, kept * x, (kept & nlos) * x, (kept & nlos) * x * x)
    for value, drawn in zip(predicted, samples, strict=True):
        se = drawn.std() / np.sqrt(n)
        assert abs(drawn.mean() - value) <= 5 * se + 1e-6


def test_the_estimate_takes_off_the_bias_kept_nlos_ranges_leave() -> None:
    """2,000 links of a blocked line of sight (half their ranges NLOS) 6 m long: the kept
    ranges' mean is long by a link mean's sigma; corrected, by a fraction of it."""
    model = UwbErrorModel()
    rng = np.random.default_rng(4)
    rounds, links, d = 300, 2000, 6.0
    sigma = float(model.sigma(d))
    nlos = rng.random((rounds, 1, links)) < model.nlos_prob_occluded
    excess = np.where(nlos, rng.uniform(*model.nlos_excess, nlos.shape), 0.0)
    y = d + sigma * rng.standard_normal(nlos.shape) + excess
    kept = reject_outliers_static(y, model.sigma(y)).ranges
    occluded = np.ones((1, links), dtype=bool)
    corrected, link_sigma = _without_nlos_leak(model, kept, occluded, lambda r: 0.0 * r)
    n_kept = np.isfinite(kept).sum(axis=0)
    mean_sigma = sigma / np.sqrt(n_kept.mean())
    before = np.nanmean(kept, axis=0) - d
    after = np.nanmean(corrected, axis=0) - d
    assert before.mean() > mean_sigma
    assert abs(after.mean()) < 0.2 * mean_sigma
    # the corrected means scatter as the noise over the kept ranges and the NLOS
    # ranges' spread together predict
    predicted = np.sqrt(np.mean(sigma**2 / n_kept + link_sigma**2))
    assert 0.85 < after.std() / predicted < 1.2


def test_a_clear_link_is_left_almost_as_it_was() -> None:
    """Without a blocked line of sight (2 % NLOS) the correction is a fraction of a
    millimetre at 3 m."""
    model = UwbErrorModel()
    rng = np.random.default_rng(5)
    y = 3.0 + model.sigma(3.0) * rng.standard_normal((300, 2, 4))
    kept = reject_outliers_static(y, model.sigma(y)).ranges
    corrected, link_sigma = _without_nlos_leak(model, kept, None, model.field_sigma)
    shift = np.nanmean(kept - corrected, axis=0)
    assert np.all(np.abs(shift) < 5e-4) and np.all(link_sigma < 1e-3)
