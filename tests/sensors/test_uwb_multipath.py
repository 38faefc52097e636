"""Position-dependent UWB multipath: the field's statistics, and a standing fix that counts it.

The field (random Fourier features of a squared-exponential covariance) is
checked against its own definition; the platform fix's covariance against the
scatter of seeded simulated fixes with the multipath on.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.positioning.uwb_platform import locate_platform
from fabflow.positioning.uwb_platform_model import rotz
from fabflow.sensors.uwb import (
    PAPER_ANCHORS_3D,
    UwbErrorModel,
    calibration_campaign,
    draw_bias,
    simulate_ranges,
)
from fabflow.sensors.uwb_multipath import draw_multipath

TAGS = np.array([[0.8, 0.0, 1.5], [-0.8, 0.0, 1.5]])
TRUTH = np.array([1.6, 2.2, 0.0, np.radians(30.0)])


@settings(max_examples=30, deadline=None)
@given(
    sigma=st.floats(0.001, 0.2),
    length=st.floats(0.1, 3.0),
    seed=st.integers(0, 2**31),
    point=st.lists(st.floats(-20.0, 20.0), min_size=3, max_size=3),
)
def test_the_field_is_bounded_finite_and_stays_where_the_tag_stays(
    sigma: float, length: float, seed: int, point: list[float]
) -> None:
    field = draw_multipath(4, sigma, length, np.random.default_rng(seed))
    x = np.array(point)
    v = field(np.stack([x, x]))
    assert v.shape == (2, 4) and np.isfinite(v).all()
    np.testing.assert_array_equal(v[0], v[1])  # the same place, the same error
    # a sum of K cosines of amplitude sigma sqrt(2 / K)
    assert np.abs(v).max() <= sigma * np.sqrt(2.0 * field.phases.shape[1]) + 1e-12
    # the plane's field is the 3-D field's section at height 0
    np.testing.assert_allclose(field(x[None, :2]), field(np.r_[x[:2], 0.0][None]), atol=1e-12)


def test_the_field_has_its_deviation_and_correlation_length() -> None:
    """Over many places and draws: standard deviation sigma, and the correlation at a
    distance ``h`` close to ``exp(-h^2 / (2 L^2))``."""
    sigma, length = 0.03, 0.5
    rng = np.random.default_rng(1)
    x = rng.uniform(0.0, 8.0, (4000, 3))
    step = np.array([1.0, 0.0, 0.0])
    values, shifted = [], {h: [] for h in (0.25, 0.5, 1.0)}
    for _ in range(20):
        field = draw_multipath(4, sigma, length, rng)
        values.append(field(x))
        for h in shifted:
            shifted[h].append(np.stack([field(x), field(x + h * step)]))
    assert np.std(np.concatenate(values)) == pytest.approx(sigma, rel=0.05)
    for h, pairs in shifted.items():
        a, b = (np.concatenate([p[i] for p in pairs]).ravel() for i in (0, 1))
        expected = np.exp(-(h**2) / (2 * length**2))
        assert np.corrcoef(a, b)[0, 1] == pytest.approx(expected, abs=0.05)


def test_the_simulator_adds_it_growing_with_the_range() -> None:
    """Tags on a ring round one anchor, the white noise off: the range errors' spread
    at 1 m is multipath_field_sigma, and grows by multipath_field_growth per metre."""
    model = dataclasses.replace(
        UwbErrorModel.gaussian(1e-12), multipath_field_sigma=0.03, multipath_field_growth=0.2
    )
    anchor = np.zeros((1, 3))
    spread = {}
    for d in (1.0, 4.0):
        errors = []
        for seed in range(300):
            rng = np.random.default_rng(seed)
            bias = draw_bias(1, model, rng)
            angle = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
            tags = d * np.c_[np.cos(angle), np.sin(angle), np.zeros_like(angle)]
            sim = simulate_ranges(anchor, tags, model, rng, bias=bias)
            errors.append(sim.ranges - sim.true_ranges)
        spread[d] = np.std(np.concatenate(errors))
    assert spread[1.0] == pytest.approx(0.03, rel=0.1)
    assert spread[4.0] == pytest.approx(0.03 * (1.0 + 0.2 * 3.0), rel=0.1)


def test_ranges_of_many_tags_and_epochs_take_each_tags_place() -> None:
    model = dataclasses.replace(UwbErrorModel.gaussian(1e-12), multipath_field_sigma=0.03)
    rng = np.random.default_rng(3)
    bias = draw_bias(4, model, rng)
    tags = rng.uniform(0.0, 4.0, (5, 2, 3))  # (epochs, tags, xyz)
    sim = simulate_ranges(PAPER_ANCHORS_3D, tags, model, rng, bias=bias)
    assert sim.ranges.shape == (5, 2, 4)
    one = simulate_ranges(PAPER_ANCHORS_3D, tags[3, 1], model, rng, bias=bias)
    np.testing.assert_allclose(sim.ranges[3, 1], one.ranges, atol=1e-9)


def test_with_the_multipath_off_the_random_stream_is_untouched() -> None:
    """Seeded results of every existing caller stay as they were: with the multipath
    off, drawing the installation and its calibration takes nothing more from the
    generator."""
    model = UwbErrorModel()
    a, b = np.random.default_rng(7), np.random.default_rng(7)
    bias = draw_bias(4, model, a)
    calibration_campaign(model, bias, a)
    lo, hi = model.offset_range
    b.uniform(lo, hi, 4), b.standard_normal(4)  # the offsets and scales
    distances = np.arange(0.5, 10.0 + 1e-9, 0.5)
    b.standard_normal((distances.size, 200, 4))  # the campaign's noise
    assert a.random() == b.random()


def _fixes(link_sigma: float | None, runs: int = 60) -> np.ndarray:
    """Normalized errors (x, y, yaw) of seeded standing fixes with 3 cm multipath."""
    model = dataclasses.replace(UwbErrorModel.gaussian(0.05), multipath_field_sigma=0.03)
    tags = TRUTH[:3] + TAGS @ rotz(TRUTH[3]).T
    out = []
    for seed in range(runs):
        rng = np.random.default_rng(seed)
        bias = draw_bias(4, model, rng)
        truth = np.broadcast_to(tags, (300, 2, 3))
        ranges = simulate_ranges(PAPER_ANCHORS_3D, truth, model, rng, bias=bias).ranges
        fix = locate_platform(
            PAPER_ANCHORS_3D, ranges, TAGS, model.sigma,
            link_sigma=None if link_sigma is None else model.field_sigma,
        )  # fmt: skip
        e = fix.state - TRUTH
        e[3] = np.angle(np.exp(1j * e[3]))
        idx = [0, 1, 3]
        C = fix.covariance[np.ix_(idx, idx)]
        out.append(e[idx] @ np.linalg.solve(C, e[idx]))
    return np.array(out)


def test_a_standing_fix_counts_the_multipath_the_dwell_does_not_average_out() -> None:
    """300 epochs average the white noise away but not the multipath: a covariance of the
    white noise alone is far too small (normalized squared errors in the hundreds);
    with each link's multipath in it, their mean is near its 3 degrees of freedom."""
    counted = _fixes(link_sigma=0.03)
    ignored = _fixes(link_sigma=None)
    assert 2.0 < counted.mean() < 4.5
    assert ignored.mean() > 10 * counted.mean()
