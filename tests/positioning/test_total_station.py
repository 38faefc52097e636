"""Total station localization: polar model, registration, outliers, degenerate sets, three-point."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.polar import (
    ARCSEC,
    GON,
    INSTRUMENTS,
    cartesian_to_polar,
    make_instrument,
    polar_covariance,
    polar_jacobian,
    polar_to_cartesian,
    to_world,
)
from fabflow.positioning.registration import register_points
from fabflow.positioning.result import BasePose
from fabflow.positioning.rigid_fit import kabsch, refine_registration, register_leveled
from fabflow.positioning.three_point import (
    localize_three_point,
    three_point_base_points,
    three_point_localization,
)
from fabflow.sensors.total_station import measure_points, simulate_polar
from fabflow.transforms.se3 import apply_T, inv_T, make_T, pose_error
from fabflow.transforms.so3 import exp_so3

MS50 = INSTRUMENTS["leica_ms50"]


def random_pose(rng: np.random.Generator, scale: float = 10.0) -> np.ndarray:
    return make_T(exp_so3(rng.normal(size=3)), rng.uniform(-scale, scale, 3))


def spread_points(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform([0.3, -2.0, 0.1], [2.2, 2.0, 2.0], (n, 3))


def observe(
    rng: np.random.Generator, T_world_base: np.ndarray, P: np.ndarray, T_world_instrument=None
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy world points and covariances of base points P seen by an MS50."""
    T_wi = (
        make_T(exp_so3([0, 0, 0.4]), [-8.0, -6.0, 1.6])
        if T_world_instrument is None
        else (T_world_instrument)
    )
    local = apply_T(inv_T(T_wi), apply_T(T_world_base, P))
    m, c = measure_points(local, MS50, rng)
    M, C = to_world(T_wi, m, c)
    assert C is not None
    return M, C


# ------------------------------------------------------------------ polar model


def test_polar_round_trip_and_conventions() -> None:
    # Hz = 100 gon points along +x, V = 100 gon is horizontal
    p = polar_to_cartesian(100 * GON, 100 * GON, 5.0)
    np.testing.assert_allclose(p, [5.0, 0.0, 0.0], atol=1e-12)
    p = polar_to_cartesian(0.0, 50 * GON, 2.0, instrument_height=1.5, prism_height=0.2)
    np.testing.assert_allclose(p, [0.0, np.sqrt(2.0), np.sqrt(2.0) + 1.3], atol=1e-12)
    rng = np.random.default_rng(1)
    pts = rng.uniform(-20, 20, (50, 3))
    back = polar_to_cartesian(*cartesian_to_polar(pts))
    np.testing.assert_allclose(back, pts, atol=1e-10)


def test_polar_jacobian_matches_finite_differences() -> None:
    hz, v, sd = 1.1, 1.3, 7.5
    J = polar_jacobian(hz, v, sd)
    eps = 1e-7
    for k, (dh, dv, ds) in enumerate(np.eye(3) * eps):
        fd = (polar_to_cartesian(hz + dh, v + dv, sd + ds) - polar_to_cartesian(hz, v, sd)) / eps
        np.testing.assert_allclose(J[:, k], fd, atol=1e-5)


def test_polar_covariance_matches_sampling() -> None:
    rng = np.random.default_rng(2)
    inst = make_instrument("custom", 2.0, 0.0, 50.0)  # large angles so both terms show
    p = np.array([6.0, 8.0, 1.0])
    samples, _ = measure_points(np.broadcast_to(p, (20000, 3)), inst, rng)
    emp = np.cov(samples.T)
    C = polar_covariance(*cartesian_to_polar(p), inst)
    np.testing.assert_allclose(emp, C, atol=0.08 * np.abs(C).max())
    # the needle: 2 mm along the line of sight, 50" x 10 m = 2.4 mm across
    w = np.linalg.eigvalsh(C)
    assert np.sqrt(w[-1]) == pytest.approx(10.05 * 50 * ARCSEC, rel=0.02)


def test_instrument_presets_and_errors() -> None:
    assert MS50.sigma_distance(100.0) == pytest.approx(0.001 + 1.5e-4)
    assert INSTRUMENTS["hilti_pos150"].angle_sigma == pytest.approx(5 * ARCSEC)
    inst = make_instrument("leica_ms50", angle_sigma_arcsec=0.5)
    assert inst.angle_sigma == pytest.approx(0.5 * ARCSEC) and inst.distance_sigma == 0.001
    with pytest.raises(InputError, match="missing distance_ppm"):
        make_instrument("custom", 1.0, None, 1.0)
    with pytest.raises(InputError, match="unknown instrument"):
        make_instrument("theodolite")


# ------------------------------------------------------------------ registration


@settings(deadline=None, max_examples=20)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 10))
def test_zero_noise_exact(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    P = spread_points(rng, n)
    M = apply_T(T, P)
    for method in ("closed_form", "optimize"):
        reg = register_points(P, M, method=method)
        np.testing.assert_allclose(reg.T_world_base, T, atol=1e-7)
        assert reg.rmse < 1e-7
        assert reg.residuals.shape == (n, 3)
        assert reg.covariance.shape == (6, 6)
    weights = rng.uniform(0.5, 2.0, n)
    reg = register_points(P, M, weights)
    np.testing.assert_allclose(reg.T_world_base, T, atol=1e-9)


@settings(deadline=None, max_examples=30)
@given(seed=st.integers(0, 2**31 - 1))
def test_planar_points_never_reflect(seed: int) -> None:
    # planar (and three-point) sets are where a naive SVD fit returns a reflection
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    P = spread_points(rng, 4)
    P[:, 2] = 0.5
    M = apply_T(T, P) + rng.normal(0, 1e-3, (4, 3))
    R, _ = kabsch(P, M)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # (three random points can be nearly collinear; then the rotation is ill-posed)
    assume(np.linalg.svd(P[:3] - P[:3].mean(axis=0), compute_uv=False)[1] > 0.05)
    R3, _ = kabsch(P[:3], apply_T(T, P[:3]))
    np.testing.assert_allclose(R3, T[:3, :3], atol=1e-9)


@settings(deadline=None, max_examples=10)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 8))
def test_closed_form_and_optimization_agree(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    P = spread_points(rng, n)
    M = apply_T(T, P) + rng.normal(0, 2e-3, (n, 3))
    a = register_points(P, M)
    b = register_points(P, M, method="optimize")
    np.testing.assert_allclose(pose_error(a.T_world_base, b.T_world_base), 0.0, atol=1e-7)
    assert a.rmse == pytest.approx(b.rmse, rel=1e-5, abs=1e-9)


def test_batched_kabsch_equals_single() -> None:
    rng = np.random.default_rng(3)
    P = rng.normal(size=(7, 5, 3))
    M = rng.normal(size=(7, 5, 3))
    w = rng.uniform(0.1, 1, (7, 5))
    R, t = kabsch(P, M, w)
    for k in range(7):
        Rk, tk = kabsch(P[k], M[k], w[k])
        np.testing.assert_allclose(R[k], Rk, atol=1e-12)
        np.testing.assert_allclose(t[k], tk, atol=1e-12)


def observe_batch(
    rng: np.random.Generator, T_world_base: np.ndarray, P: np.ndarray, runs: int
) -> tuple[np.ndarray, np.ndarray]:
    """``runs`` independent noisy observations of the base points P (batched)."""
    T_wi = make_T(exp_so3([0, 0, 0.4]), [-8.0, -6.0, 1.6])
    local = apply_T(inv_T(T_wi), apply_T(T_world_base, P))
    m, c = measure_points(np.broadcast_to(local, (runs, *P.shape)), MS50, rng)
    M, C = to_world(T_wi, m, c)
    assert C is not None
    return M, C


def test_covariance_is_consistent_with_errors() -> None:
    """Monte Carlo: the predicted 6x6 covariance explains the actual pose errors."""
    rng = np.random.default_rng(4)
    T = make_T(exp_so3([0.01, -0.02, 0.8]), [3.0, 2.0, 0.6])
    P = spread_points(rng, 5)
    M, C = observe_batch(rng, T, P, 1000)
    Pb = np.broadcast_to(P, M.shape)
    R0, t0 = kabsch(Pb, M, 3.0 / np.trace(C, axis1=-2, axis2=-1))
    R1, t1, _ = refine_registration(R0, t0, Pb, M, np.linalg.inv(C))
    e = pose_error(make_T(R1, t1), T)
    # register_points is exactly this estimator ...
    one = register_points(P, M[0], point_cov=C[0])
    np.testing.assert_allclose(one.T_world_base, make_T(R1[0], t1[0]), atol=1e-12)
    # ... and its covariance predicts the spread of the errors
    nees = np.einsum("ni,ij,nj->n", e, np.linalg.inv(one.covariance), e)
    assert 6 * 0.9 < nees.mean() < 6 * 1.1
    np.testing.assert_allclose(
        np.sqrt(np.diag(np.cov(e.T))), np.sqrt(np.diag(one.covariance)), rtol=0.12
    )


def test_prism_centring_and_atmosphere_are_simulated_and_in_the_covariance() -> None:
    """2 mm centring and 20 ppm of atmosphere: the point covariances carry them and the
    pose covariance predicts the errors; the data sheet's alone would be over-confident."""
    rng = np.random.default_rng(6)
    field = make_instrument("leica_ms50", prism_centring_mm=2.0, atmosphere_ppm=20.0)
    T = make_T(exp_so3([0.01, -0.02, 0.8]), [3.0, 2.0, 0.6])
    P = spread_points(rng, 5)
    T_wi = make_T(exp_so3([0, 0, 0.4]), [-8.0, -6.0, 1.6])
    local = apply_T(inv_T(T_wi), apply_T(T, P))
    # one set-up per run: the atmosphere's scale is drawn per call
    runs = [measure_points(local, field, rng) for _ in range(400)]
    scatter = np.std([m - local for m, _ in runs], axis=0).mean()
    assert scatter > 1.5e-3  # the centring dominates MS50's 1 mm + 1"
    hz, v, sd = cartesian_to_polar(local)
    plain = polar_covariance(hz, v, sd, MS50)
    no_centring = make_instrument("leica_ms50", atmosphere_ppm=20.0)
    np.testing.assert_allclose(
        polar_covariance(hz, v, sd, field) - polar_covariance(hz, v, sd, no_centring),
        np.broadcast_to(4e-6 * np.eye(3), plain.shape),
        atol=1e-15,
    )
    # the atmosphere adds (20 ppm x distance)^2 along the line of sight only
    u = local / np.linalg.norm(local, axis=1)[:, None]
    extra = polar_covariance(hz, v, sd, no_centring) - plain
    along = np.einsum("ni,nij,nj->n", u, extra, u)
    np.testing.assert_allclose(along, (20e-6 * sd) ** 2, rtol=1e-6)
    nees_field, nees_sheet = [], []
    for m, c in runs:
        M, C = to_world(T_wi, m, c)
        fit = register_points(P, M, point_cov=C)
        e = pose_error(fit.T_world_base, T)
        nees_field.append(e @ np.linalg.solve(fit.covariance, e))
        _, C0 = to_world(T_wi, m, polar_covariance(*cartesian_to_polar(m), MS50))
        cov0 = register_points(P, M, point_cov=C0).covariance
        nees_sheet.append(e @ np.linalg.solve(cov0, e))
    assert 6 * 0.8 < np.mean(nees_field) < 6 * 1.2, np.mean(nees_field)
    assert np.mean(nees_sheet) > 6 * 2, np.mean(nees_sheet)


def test_full_covariance_beats_isotropic_fit() -> None:
    rng = np.random.default_rng(5)
    T = make_T(exp_so3([0.0, 0.0, 1.2]), [5.0, -1.0, 0.6])
    P = spread_points(rng, 4)
    M, C = observe_batch(rng, T, P, 500)
    Pb = np.broadcast_to(P, M.shape)
    R0, t0 = kabsch(Pb, M)
    R1, t1, _ = refine_registration(R0, t0, Pb, M, np.linalg.inv(C))
    pos_iso = np.linalg.norm(pose_error(make_T(R0, t0), T)[:, :3], axis=1).mean()
    pos_full = np.linalg.norm(pose_error(make_T(R1, t1), T)[:, :3], axis=1).mean()
    assert pos_full < 0.8 * pos_iso


def test_to_base_pose_round_trips() -> None:
    rng = np.random.default_rng(6)
    T = random_pose(rng)
    P = spread_points(rng, 5)
    M, C = observe(rng, T, P)
    bp = register_points(P, M, point_cov=C).to_base_pose(station="S2")
    assert isinstance(bp, BasePose) and bp.method == "total_station" and bp.station == "S2"
    back = BasePose.from_dict(bp.to_dict())
    np.testing.assert_allclose(back.T_world_base, bp.T_world_base)
    np.testing.assert_allclose(back.covariance, bp.covariance)
    assert back.quality["n_points"] == 5 and "outlier_test" in back.quality


# ------------------------------------------------------------------ bad readings


def test_single_bad_prism_is_found_and_rejected() -> None:
    rng = np.random.default_rng(7)
    T = make_T(exp_so3([0.0, 0.0, -0.4]), [4.0, 3.0, 0.5])
    P = spread_points(rng, 6)
    M, C = observe(rng, T, P)
    clean = register_points(P, M, point_cov=C)
    assert clean.outlier_test is not None and not clean.outlier_test.flagged
    M_bad = M.copy()
    M_bad[3] += [0.004, -0.003, 0.0]  # 5 mm: a prism knocked or the wrong target locked
    reg = register_points(P, M_bad, point_cov=C, reject_outlier=True)
    assert reg.outlier_test is not None
    assert reg.outlier_test.flagged and reg.outlier_test.index == 3
    assert reg.rejected == (3,)
    assert np.linalg.norm(reg.residuals[3]) > 0.004
    err = pose_error(reg.T_world_base, T)
    assert np.linalg.norm(err[:3]) < 1e-3
    kept = register_points(P, M_bad, point_cov=C)
    assert kept.rejected == () and kept.outlier_test is not None and kept.outlier_test.flagged


def test_bad_prism_found_with_unknown_noise_level() -> None:
    rng = np.random.default_rng(8)
    T = random_pose(rng)
    P = spread_points(rng, 7)
    M = apply_T(T, P) + rng.normal(0, 1e-3, (7, 3))
    M[5] += [0.0, 0.02, 0.01]
    reg = register_points(P, M, reject_outlier=True)
    assert reg.outlier_test is not None and not reg.outlier_test.known_sigma
    assert reg.outlier_test.flagged and reg.rejected == (5,)
    assert reg.rmse < 3e-3


def test_false_alarm_rate_is_near_alpha() -> None:
    rng = np.random.default_rng(9)
    T = make_T(np.eye(3), [2.0, 2.0, 0.5])
    P = spread_points(rng, 6)
    alarms = 0
    for _ in range(60):
        M, C = observe(rng, T, P)
        test = register_points(P, M, point_cov=C, alpha=0.05).outlier_test
        assert test is not None
        alarms += test.flagged
    assert alarms <= 8  # alpha = 5 %: about 3 expected


def test_three_points_have_no_outlier_test() -> None:
    rng = np.random.default_rng(10)
    P = spread_points(rng, 3)
    reg = register_points(P, P + 1.0)
    assert reg.outlier_test is None and reg.variance_factor < 1e-20


# ------------------------------------------------------------------ bad input


def test_degenerate_point_sets_are_refused() -> None:
    line = np.outer(np.linspace(0, 2, 5), [1.0, 0.5, 0.2])
    with pytest.raises(LocalizationError, match="collinear"):
        register_points(line, line + 1.0)
    nearly = line + np.random.default_rng(0).normal(0, 1e-6, line.shape)
    with pytest.raises(LocalizationError, match="collinear"):
        register_points(nearly, nearly)
    same = np.ones((4, 3))
    with pytest.raises(LocalizationError, match="coincident"):
        register_points(same, same)
    with pytest.raises(LocalizationError, match="at least 3"):
        register_points(np.eye(3)[:2], np.eye(3)[:2])


def test_bad_arrays_are_input_errors() -> None:
    P = spread_points(np.random.default_rng(0), 4)
    with pytest.raises(InputError, match=r"shape \(n, 3\)"):
        register_points(P[:, :2], P[:, :2])
    with pytest.raises(InputError, match="expected 4"):
        register_points(P, P[:3])
    Q = P.copy()
    Q[2, 1] = np.nan
    with pytest.raises(InputError, match="row 2 is not finite"):
        register_points(P, Q)
    with pytest.raises(InputError, match="weights"):
        register_points(P, P, weights=[1, -1, 1, 1])
    with pytest.raises(InputError, match="point_cov"):
        register_points(P, P, point_cov=np.zeros((3, 3, 3)))
    with pytest.raises(InputError, match="positive definite"):
        register_points(P, P, point_cov=np.zeros((4, 3, 3)))
    with pytest.raises(InputError, match="unknown method"):
        register_points(P, P, method="icp")  # type: ignore[arg-type]


# ------------------------------------------------------------------ three-point, levelled


def test_three_point_localization_exact_and_covariance() -> None:
    rng = np.random.default_rng(11)
    T = make_T(exp_so3([0.02, -0.01, 2.5]), [7.0, -3.0, 0.6])
    P = three_point_base_points([0.8, -0.4, 0.9], 0.8)
    reg = localize_three_point(apply_T(T, P), P[0], 0.8)
    np.testing.assert_allclose(reg.T_world_base, T, atol=1e-12)
    assert reg.method == "three_point" and reg.rmse < 1e-12
    M, C = observe_batch(rng, T, P, 2000)
    R, t = three_point_localization(M, np.broadcast_to(P[1], (2000, 3)))
    emp = np.sqrt(np.diag(np.cov(pose_error(make_T(R, t), T).T)))
    one = localize_three_point(M[0], P[0], 0.8, point_cov=C[0])
    np.testing.assert_allclose(one.T_world_base, make_T(R[0], t[0]), atol=1e-12)
    np.testing.assert_allclose(emp, np.sqrt(np.diag(one.covariance)), rtol=0.12)
    with pytest.raises(InputError, match="positive"):
        localize_three_point(apply_T(T, P), P[0], 0.0)


def test_levelled_fit_exact() -> None:
    rng = np.random.default_rng(12)
    T = make_T(exp_so3([0, 0, -2.0]), [3.0, 1.0, 1.6])
    L = rng.uniform(-5, 5, (6, 3))
    R, t = register_leveled(L, apply_T(T, L))
    np.testing.assert_allclose(make_T(R, t), T, atol=1e-12)


def test_zero_weights_leave_points_out() -> None:
    rng = np.random.default_rng(13)
    T = random_pose(rng)
    P = spread_points(rng, 5)
    M = apply_T(T, P)
    M[4] += 1.0  # wildly wrong, but weighted out
    reg = register_points(P, M, weights=[1, 1, 1, 1, 0])
    np.testing.assert_allclose(reg.T_world_base, T, atol=1e-9)
    assert reg.rejected == (4,) and np.linalg.norm(reg.residuals[4]) == pytest.approx(np.sqrt(3))
    with pytest.raises(LocalizationError, match="positive weight"):
        register_points(P, M, weights=[1, 1, 0, 0, 0])


def test_two_faults_on_a_nearly_collinear_set_fail_without_a_traceback() -> None:
    # four points on one line and one off it: the point the w-test blames may be the
    # only one whose removal leaves the rest degenerate; the pose then fails
    rng = np.random.default_rng(0)
    P = np.array([[0, 0, 0.5], [0.5, 0, 0.5], [1.0, 0, 0.5], [1.5, 0, 0.5], [0.7, 0.8, 0.9]])
    C = np.array([np.eye(3) * (5e-4) ** 2] * 5)
    statuses = set()
    for _ in range(200):
        M = P + rng.normal(0, 5e-4, P.shape)
        k = rng.choice(5, 2, replace=False)
        M[k] += rng.normal(0, 0.02, (2, 3))
        try:
            reg = register_points(P, M, point_cov=C, reject_outlier=True, identify_prisms=False)
        except LocalizationError:
            continue
        assert reg.integrity is not None
        statuses.add(reg.integrity.status)
        if reg.integrity.status != "failed":
            assert reg.integrity.global_test["passed"]
    assert "failed" in statuses


def test_the_atmosphere_stretches_a_set_up_s_distances_alike() -> None:
    """One scale error per call (one set-up): within a call the distances' relative
    errors agree, between calls they differ by the stated ppm."""
    rng = np.random.default_rng(8)
    exact = make_instrument("custom", 0.01, 0.0, 0.01, atmosphere_ppm=500.0)
    P = rng.uniform(-40.0, 40.0, (20, 3)) + np.array([0.0, 0.0, 60.0])
    _, _, sd_true = cartesian_to_polar(P)
    scales = np.array([simulate_polar(P, exact, rng)[2] / sd_true - 1.0 for _ in range(300)])
    assert scales.std(axis=1).max() < 2e-6  # within a set-up: one scale (0.01 mm noise)
    assert np.std(scales[:, 0]) == pytest.approx(500e-6, rel=0.15)  # between set-ups
