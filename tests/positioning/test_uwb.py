"""UWB multilateration, CRLB, calibration, outlier rejection, platform pose, station simulation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.uwb import crlb, horizontal_ranges, locate
from fabflow.positioning.uwb_calibration import RangeCalibration, reject_outliers, running_median
from fabflow.positioning.uwb_platform import locate_platform
from fabflow.sensors.uwb import (
    PAPER_ANCHORS_3D,
    PAPER_POINTS_3D,
    AnchorBias,
    UwbErrorModel,
    calibration_campaign,
    draw_bias,
    segments_occluded,
    simulate_ranges,
)
from fabflow.sensors.uwb_trajectories import PlanarTrajectory

SQUARE = np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 6.0], [0.0, 6.0]])


def exact_ranges(anchors: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(points[:, None, :] - anchors[None], axis=-1)


@pytest.mark.parametrize("method", ["ls", "wls", "wls-t"])
@pytest.mark.parametrize("anchors", [SQUARE, PAPER_ANCHORS_3D], ids=["2d", "3d"])
def test_exact_solution_without_noise(method: str, anchors: np.ndarray) -> None:
    rng = np.random.default_rng(0)
    dim = anchors.shape[1]
    points = rng.uniform(0.5, 4.0, (50, dim))
    fix = locate(anchors, exact_ranges(anchors, points), method=method, sigma=0.05)
    assert fix.valid.all()
    np.testing.assert_allclose(fix.positions, points, atol=1e-8)
    assert fix.covariances.shape == (50, dim, dim)
    assert np.all(np.linalg.eigvalsh(fix.covariances) > 0)
    np.testing.assert_allclose(fix.residuals, 0.0, atol=1e-8)


@settings(deadline=None, max_examples=30)
@given(
    seed=st.integers(0, 2**31 - 1),
    n_anchors=st.integers(4, 8),
    method=st.sampled_from(["ls", "wls", "wls-t"]),
)
def test_exact_solution_random_geometry(seed: int, n_anchors: int, method: str) -> None:
    rng = np.random.default_rng(seed)
    anchors = rng.uniform(-5, 5, (n_anchors, 3))
    points = rng.uniform(-3, 3, (10, 3))
    fix = locate(anchors, exact_ranges(anchors, points), method=method, sigma=0.05)
    ok = fix.valid
    # a random layout can be nearly degenerate for a point; those epochs are flagged, not wrong
    assert ok.mean() >= 0.8
    np.testing.assert_allclose(fix.positions[ok], points[ok], atol=1e-5)


def test_missing_ranges_and_too_few() -> None:
    anchors = np.vstack([PAPER_ANCHORS_3D, [[2.4, 3.0, 3.0]]])
    points = PAPER_POINTS_3D
    r = exact_ranges(anchors, points)
    r[0, 1] = np.nan  # 4 left: still solvable
    r[1, [0, 2]] = np.nan  # 3 left: too few in 3D
    fix = locate(anchors, r, method="wls-t", sigma=0.05)
    assert fix.valid[0] and not fix.valid[1]
    assert fix.too_few[1] and not fix.too_few[0]
    assert np.isnan(fix.positions[1]).all()
    np.testing.assert_allclose(fix.positions[0], points[0], atol=1e-8)
    assert np.isnan(fix.residuals[0, 1])
    np.testing.assert_allclose(fix.positions[2:], points[2:], atol=1e-8)


def test_degenerate_anchor_geometry_raises() -> None:
    collinear = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]])
    with pytest.raises(LocalizationError, match="collinear"):
        locate(collinear, np.ones((1, 4)))
    coplanar = np.array([[0, 0, 2.2], [6, 0, 2.2], [6, 6, 2.2], [0, 6, 2.2]], dtype=float)
    with pytest.raises(LocalizationError, match="coplanar"):
        locate(coplanar, np.ones((1, 4)))


def test_degenerate_epoch_is_flagged() -> None:
    anchors = np.array([[0.0, 0.0], [2.0, 0.0], [4.0, 0.0], [2.0, 5.0]])
    p = np.array([[1.0, 2.0]])
    r = exact_ranges(anchors, p)
    r[0, 3] = np.nan  # the three left are collinear
    for method in ("ls", "wls", "wls-t"):
        fix = locate(anchors, r, method=method)
        assert not fix.valid[0] and fix.degenerate[0] and not fix.too_few[0]


def test_bad_inputs() -> None:
    with pytest.raises(InputError, match="unknown UWB method"):
        locate(SQUARE, np.ones((2, 4)), method="chan")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="ranges must be"):
        locate(SQUARE, np.ones((2, 3)))
    with pytest.raises(InputError, match="at least 3 anchors"):
        locate(SQUARE[:2], np.ones((2, 2)))


def test_crlb_symmetric_square() -> None:
    # centre of a square: u_i at 45 degrees, information n / (2 sigma^2) per axis
    C = crlb(SQUARE, np.array([3.0, 3.0]), 0.1)
    np.testing.assert_allclose(C, np.eye(2) * 2 * 0.01 / 4)
    batch = crlb(SQUARE, np.array([[3.0, 3.0], [1.0, 2.0]]), 0.1)
    assert batch.shape == (2, 2, 2)
    with pytest.raises(LocalizationError):
        crlb(np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), np.array([5.0, 0.0]), 0.1)


def test_wls_t_reaches_crlb_and_covariance_is_consistent() -> None:
    rng = np.random.default_rng(1)
    sigma = 0.05
    for p in PAPER_POINTS_3D[[0, 4]]:
        sim = simulate_ranges(
            PAPER_ANCHORS_3D, np.broadcast_to(p, (4000, 3)), UwbErrorModel.gaussian(sigma), rng
        )
        fix = locate(PAPER_ANCHORS_3D, sim.ranges, method="wls-t", sigma=sigma)
        # only converged fixes are valid; nearly all converge
        assert fix.valid.mean() > 0.995
        err = fix.positions[fix.valid] - p
        rmse = np.sqrt(np.mean(np.sum(err**2, axis=1)))
        bound = np.sqrt(np.trace(crlb(PAPER_ANCHORS_3D, p, sigma)))
        assert rmse >= 0.95 * bound
        assert rmse <= 1.10 * bound
        np.testing.assert_allclose(
            np.cov(err.T), fix.covariances[fix.valid].mean(axis=0), rtol=0.15, atol=1e-5
        )
        assert fix.converged.mean() > 0.99


def test_distance_dependent_sigma_callable() -> None:
    model = UwbErrorModel()
    rng = np.random.default_rng(2)
    p = PAPER_POINTS_3D[1]
    sim = simulate_ranges(
        PAPER_ANCHORS_3D, np.broadcast_to(p, (2000, 3)), model.without_outliers(), rng
    )
    fix = locate(PAPER_ANCHORS_3D, sim.ranges, method="wls-t", sigma=model.sigma)
    bound = np.sqrt(np.trace(crlb(PAPER_ANCHORS_3D, p, model.sigma)))
    assert fix.valid.mean() > 0.99
    rmse = np.sqrt(np.mean(np.sum((fix.positions[fix.valid] - p) ** 2, axis=1)))
    assert 0.9 * bound < rmse < 1.15 * bound


def test_horizontal_ranges() -> None:
    r = horizontal_ranges(np.array([[5.0, 1.0]]), np.array([2.2, 2.2]), tag_z=-0.8)
    np.testing.assert_allclose(r, [[4.0, 0.0]])


# ---------------------------------------------------------------- calibration


def test_calibration_recovers_bias_and_inverts() -> None:
    rng = np.random.default_rng(3)
    model = UwbErrorModel()
    bias = draw_bias(4, model, rng)
    cal = RangeCalibration.fit(*calibration_campaign(model, bias, rng))
    np.testing.assert_allclose(cal.offset, bias.offset, atol=0.01)
    np.testing.assert_allclose(cal.scale, bias.scale, atol=0.002)
    d = np.array([[1.0, 2.0, 3.0, 4.0]])
    np.testing.assert_allclose(cal.apply(bias.offset + bias.scale * d), d, atol=0.02)
    np.testing.assert_allclose(
        cal.apply_indexed(bias.offset[[2, 0]] + bias.scale[[2, 0]] * 2.0, [2, 0]), 2.0, atol=0.02
    )


def test_calibration_errors() -> None:
    with pytest.raises(InputError, match="two distinct"):
        RangeCalibration.fit(np.array([1.0, 1.0]), np.ones((2, 3)))
    with pytest.raises(InputError, match="unknown anchors"):
        RangeCalibration.from_mapping({"A9": {"offset": 0.1}}, ["A1", "A2"])
    cal = RangeCalibration.from_mapping({"A2": {"offset": 0.1, "scale": 1.01}}, ["A1", "A2"])
    np.testing.assert_allclose(cal.offset, [0.0, 0.1])


def test_reject_outliers_running_median() -> None:
    rng = np.random.default_rng(4)
    n = 600
    truth = np.linspace(3.0, 4.0, n)[:, None] * np.ones((1, 4))
    y = truth + 0.05 * rng.standard_normal((n, 4))
    bad = rng.random((n, 4)) < 0.02
    y[bad] += rng.uniform(0.3, 1.5, bad.sum())
    y[10, 2] = -1.0
    y[20, 1] = 250.0
    rej = reject_outliers(y, 0.05, window=15, k=3.0, max_range=100.0)
    assert rej.out_of_bounds[10, 2] and rej.out_of_bounds[20, 1]
    assert rej.rejected[bad].mean() > 0.95
    assert rej.rejected[~bad].mean() < 0.02
    assert np.isnan(rej.ranges[rej.rejected]).all()


def test_running_median_causal_and_nan() -> None:
    x = np.array([1.0, 2.0, np.nan, 4.0, 100.0, 6.0])
    np.testing.assert_allclose(running_median(x, 3), [1.5, 1.5, 3.0, 52.0, 6.0, 53.0])
    np.testing.assert_allclose(running_median(x, 3, causal=True)[:2], [1.0, 1.5])


# -------------------------------------------------------------- platform pose


def _rotz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


@settings(deadline=None, max_examples=20)
@given(
    x=st.floats(0.5, 4.0),
    y=st.floats(0.5, 5.0),
    yaw=st.floats(-3.1, 3.1),
)
def test_platform_pose_exact(x: float, y: float, yaw: float) -> None:
    L = np.array([[0.8, 0.0, 1.5], [-0.8, 0.0, 1.5], [0.0, 0.5, 1.6]])
    p = np.array([x, y, 0.3])
    tags = p + L @ _rotz(yaw).T
    r = np.broadcast_to(exact_ranges(PAPER_ANCHORS_3D, tags), (5, 3, 4))
    fix = locate_platform(PAPER_ANCHORS_3D, r, L, 0.05)
    np.testing.assert_allclose(fix.state[:3], p, atol=1e-6)
    assert abs(np.angle(np.exp(1j * (fix.state[3] - yaw)))) < 1e-6
    assert fix.heading_observed


def test_platform_single_tag_needs_heading() -> None:
    L = np.array([[0.5, 0.0, 1.5]])
    p, yaw = np.array([2.0, 2.5, 0.0]), 0.4
    r = exact_ranges(PAPER_ANCHORS_3D, p + L @ _rotz(yaw).T)[None]
    with pytest.raises(LocalizationError, match="heading"):
        locate_platform(PAPER_ANCHORS_3D, r, L, 0.05)
    fix = locate_platform(PAPER_ANCHORS_3D, r, L, 0.05, heading_prior=(yaw, 0.05))
    np.testing.assert_allclose(fix.state, [*p, yaw], atol=1e-6)
    assert np.sqrt(fix.covariance[3, 3]) < 0.051


def test_segments_occluded() -> None:
    box = np.eye(4)[None]
    ext = np.array([[1.0, 1.0, 1.0]])
    starts = np.array([[-2.0, 0, 0], [-2.0, 2.0, 0], [-2.0, 0, 0]])
    ends = np.array([[2.0, 0, 0], [2.0, 2.0, 0], [-1.0, 0, 0]])
    np.testing.assert_array_equal(segments_occluded(starts, ends, box, ext), [True, False, False])


def test_simulator_error_model() -> None:
    rng = np.random.default_rng(7)
    model = UwbErrorModel()
    anchors = np.array([[0.0, 0.0, 0.0]])
    tags = np.array([[5.0, 0.0, 0.0]])
    sim = simulate_ranges(anchors, np.broadcast_to(tags, (20000, 3)), model, rng)
    frac = sim.nlos.mean()
    assert 0.015 < frac < 0.025
    clean = sim.ranges[~sim.nlos] - 5.0
    assert abs(np.std(clean) - model.sigma(5.0)) < 0.003
    excess = sim.ranges[sim.nlos] - 5.0
    assert excess.min() > 0.3 - 0.5 and excess.mean() > 0.7
    b = AnchorBias(offset=np.array([0.1]), scale=np.array([1.01]))
    gs = simulate_ranges(anchors, tags, UwbErrorModel.gaussian(0.0), rng, bias=b)
    np.testing.assert_allclose(gs.ranges, 0.1 + 1.01 * 5.0)


def test_trajectory_derivatives_are_consistent() -> None:
    traj = PlanarTrajectory(np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.5], [0.5, 2.0]]), 1.0)
    t = np.arange(0.0, traj.duration, 0.001)
    s = traj.sample(t)
    v_num = np.gradient(s.p, t, axis=0)
    a_num = np.gradient(s.v, t, axis=0)
    assert np.abs(v_num - s.v).max() < 1e-3
    assert np.percentile(np.abs(a_num - s.a), 99) < 1e-3
    np.testing.assert_allclose(s.p[0], [0, 0, 1])
    np.testing.assert_allclose(s.p[-1], [0.5, 2.0, 1.0], atol=1e-9)
    assert np.allclose(s.v[0], 0) and np.allclose(s.v[-1], 0)
    with pytest.raises(InputError):
        PlanarTrajectory(np.array([[0.0, 0.0]]), 1.0)


def test_multipath_is_time_correlated() -> None:
    import dataclasses

    model = dataclasses.replace(
        UwbErrorModel.gaussian(0.0), multipath_sigma=0.03, multipath_tau=1.0
    )
    tags = np.broadcast_to(np.array([3.0, 4.0, 0.0]), (30000, 3))
    sim = simulate_ranges(np.zeros((1, 3)), tags, model, np.random.default_rng(8), dt=1 / 60)
    e = sim.ranges[:, 0] - 5.0
    assert abs(e.std() - 0.03) < 0.005
    assert abs(np.corrcoef(e[:-60], e[60:])[0, 1] - np.exp(-1.0)) < 0.1
    with pytest.raises(InputError, match="dt"):
        simulate_ranges(np.zeros((1, 3)), tags[:10], model, np.random.default_rng(8))


def test_static_rejection_survives_half_nlos() -> None:
    from fabflow.positioning.uwb_calibration import reject_outliers_static, shortest_half_center

    rng = np.random.default_rng(9)
    y = 4.0 + 0.06 * rng.standard_normal((300, 2))
    nlos = rng.random((300, 2)) < 0.5
    y[nlos] += rng.uniform(0.3, 1.5, nlos.sum())
    centre = shortest_half_center(y)
    np.testing.assert_allclose(centre, 4.0, atol=0.08)
    assert np.all(np.abs(np.nanmedian(y, axis=0) - 4.0) > 0.05)  # the median is pulled away
    rej = reject_outliers_static(y, 0.06)
    assert rej.rejected[nlos].mean() > 0.9 and rej.rejected[~nlos].mean() < 0.02
    np.testing.assert_allclose(np.nanmean(rej.ranges, axis=0), 4.0, atol=0.015)


@settings(max_examples=150, deadline=None)
@given(
    st.integers(1, 30),
    st.integers(1, 5),
    st.sampled_from([0.1, 0.25, 0.5, 0.9]),
    st.integers(0, 2**32 - 1),
)
def test_shortest_half_center_is_each_columns_densest_interval(
    n: int, m: int, fraction: float, seed: int
) -> None:
    """The columns solved together give what each gives alone, with NaN, ties (ranges
    on a centimetre grid) and too few samples (a sorted column, its shortest window of
    ``max(2, ceil(fraction * n))`` samples, the first on ties, and that window's median)."""
    from fabflow.positioning.uwb_calibration import shortest_half_center

    rng = np.random.default_rng(seed)
    y = np.round(rng.normal(5.0, 0.1, (n, m, 2)), int(rng.integers(1, 4)))
    y[rng.random(y.shape) < rng.random()] = np.nan
    y[rng.random(y.shape) < 0.2] += rng.uniform(0.3, 1.5)
    got = shortest_half_center(y, fraction)
    assert got.shape == (m, 2)
    for j in np.ndindex(m, 2):
        v = np.sort(y[(slice(None), *j)][np.isfinite(y[(slice(None), *j)])])
        if v.size < 3:
            assert np.isnan(got[j])
            continue
        h = max(2, int(np.ceil(fraction * v.size)))
        i = int(np.argmin(v[h - 1 :] - v[: v.size - h + 1]))
        assert got[j] == np.median(v[i : i + h])


def test_shortest_half_center_ignores_infinities_and_checks_its_fraction() -> None:
    from fabflow.positioning.uwb_calibration import shortest_half_center

    finite = np.array([1.1, 1.15, 1.2, 1.3, 2.0])
    y = np.r_[[-np.inf] * 3, finite, np.inf][:, None]
    assert shortest_half_center(y)[0] == shortest_half_center(finite[:, None])[0] == 1.125
    with pytest.raises(ValueError, match="fraction"):
        shortest_half_center(y, 1.5)


def test_calibration_bias_sigma() -> None:
    rng = np.random.default_rng(10)
    model = UwbErrorModel()
    bias = draw_bias(4, model, rng)
    errs = []
    for _ in range(40):
        cal = RangeCalibration.fit(*calibration_campaign(model, bias, rng))
        errs.append(cal.apply(bias.offset + bias.scale * 4.0) - 4.0)
    predicted = cal.bias_sigma(4.0)
    assert predicted.shape == (4,)
    np.testing.assert_allclose(np.std(errs, axis=0), predicted, rtol=0.5)
    assert np.all(RangeCalibration.identity(4).bias_sigma(4.0) == 0)


@settings(deadline=None, max_examples=40)
@given(
    seed=st.integers(0, 2**31),
    offset=st.tuples(*[st.floats(-500.0, 500.0)] * 2, st.floats(-20.0, 20.0)),
)
def test_wls_fixes_move_with_the_site(seed: int, offset: tuple[float, float, float]) -> None:
    # the same anchors and ranges anywhere on the site give the same fix, moved: far from
    # the origin the squared-range model must not lose its conditioning
    rng = np.random.default_rng(seed)
    A = rng.uniform([-6, -6, 0.5], [6, 6, 3.5], (4 + seed % 3, 3))
    tag = rng.uniform([-3, -3, 0.5], [3, 3, 2.0], 3)
    r = np.linalg.norm(A - tag, axis=1)[None] + 0.02 * rng.standard_normal((5, len(A)))
    near = locate(A, r, method="wls", sigma=0.02)
    far = locate(A + np.asarray(offset), r, method="wls", sigma=0.02)
    np.testing.assert_array_equal(near.valid, far.valid)
    assume(near.valid.all())
    np.testing.assert_allclose(far.positions - np.asarray(offset), near.positions, atol=1e-6)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), rounds=st.integers(1, 40), growth=st.floats(0.0, 0.02))
def test_a_standing_tag_ranges_as_the_same_positions_written_out(
    seed: int, rounds: int, growth: float
) -> None:
    # a tag broadcast over the epochs takes its distances once: the ranges, truth and
    # NLOS flags are those of the same positions written out, draw for draw
    model = UwbErrorModel(sigma_1m=0.033, growth=growth)
    tags = np.random.default_rng(seed).uniform(0.0, 5.0, (2, 3))
    standing = np.broadcast_to(tags, (rounds, 2, 3))
    occluded = np.broadcast_to([[True, False, False, True]] * 2, (rounds, 2, 4))
    bias = draw_bias(4, model, np.random.default_rng(seed + 1))
    a, b = (
        simulate_ranges(PAPER_ANCHORS_3D, t, model, np.random.default_rng(seed), bias, occluded)
        for t in (standing, standing.copy())
    )
    for name in ("ranges", "true_ranges", "nlos"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert a.true_ranges.flags.writeable
