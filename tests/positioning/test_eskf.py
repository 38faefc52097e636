"""UWB/IMU error-state Kalman filter, the constant-velocity EKF baseline and the IMU simulator."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.positioning.cv_ekf import cv_ekf_track
from fabflow.positioning.eskf import (
    Eskf,
    EskfParams,
    _exp_transpose,
    _quat_rotate_right,
    _quat_to_R,
    default_covariance,
    initial_attitude,
    pose_covariance_world,
    run_eskf,
)
from fabflow.positioning.eskf_integrity import (
    BiasMonitor,
    consistency,
    eskf_integrity,
)
from fabflow.positioning.uwb import locate
from fabflow.positioning.uwb_calibration import RangeCalibration, reject_outliers
from fabflow.sensors.imu import ImuErrorModel, simulate_imu
from fabflow.sensors.uwb import (
    PAPER_ANCHORS_3D,
    UwbErrorModel,
    calibration_campaign,
    draw_bias,
    ranging_schedule,
    simulate_ranges,
)
from fabflow.sensors.uwb_trajectories import PlanarTrajectory
from fabflow.transforms.so3 import exp_so3, matrix_from_quat, quat_from_rotvec

LINE = PlanarTrajectory(np.array([[1.2, 1.5], [3.0, 3.0]]), 2.0, speed=0.3, rest_s=2.0)


@settings(deadline=None, max_examples=40)
@given(
    q=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1),
    th=st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3),
)
def test_hot_loop_rotations_match_transforms(q: list[float], th: list[float]) -> None:
    q = np.array(q) / np.linalg.norm(q)
    th = np.array(th)
    np.testing.assert_allclose(_quat_to_R(q), matrix_from_quat(q), atol=1e-12)
    np.testing.assert_allclose(
        _quat_to_R(_quat_rotate_right(q, th)), matrix_from_quat(q) @ exp_so3(th), atol=1e-12
    )
    np.testing.assert_allclose(_exp_transpose(th), exp_so3(th).T, atol=1e-12)


def test_range_jacobian_matches_numerical() -> None:
    lever = np.array([0.3, -0.2, 0.5])
    q = quat_from_rotvec(np.array([0.1, -0.2, 0.7]))
    f = Eskf(np.array([1.0, 2.0, 1.5]), np.zeros(3), q, default_covariance())
    anchor = PAPER_ANCHORS_3D[3]

    def h(dx: np.ndarray) -> float:
        R = matrix_from_quat(q) @ exp_so3(dx[6:9])
        return float(np.linalg.norm(f.p + dx[0:3] + R @ lever - anchor))

    f.update_range(anchor, h(np.zeros(15)), 1e9, lever)  # tiny-weight update to fill H
    H = f._H.copy()
    eps = 1e-6
    num = np.array([(h(eps * e) - h(-eps * e)) / (2 * eps) for e in np.eye(15)])
    np.testing.assert_allclose(H, num, atol=1e-7)


def test_dead_reckoning_with_perfect_imu_follows_the_trajectory() -> None:
    rng = np.random.default_rng(1)
    perfect = ImuErrorModel(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    imu = simulate_imu(LINE, 100.0, perfect, rng)
    truth = LINE.sample(imu.t)
    q0 = quat_from_rotvec(np.array([0.0, 0.0, truth.yaw[0]]))
    f = Eskf(truth.p[0], truth.v[0], q0, default_covariance())
    track = run_eskf(
        f,
        imu.t,
        imu.accel,
        imu.gyro,
        np.zeros(0),
        np.zeros(0, int),
        np.zeros(0),
        PAPER_ANCHORS_3D,
        0.05,
    )
    err = np.linalg.norm(track.p - truth.p, axis=1)
    assert err.max() < 0.01
    assert track.n_updates == 0
    # no range bounds the error: the pose is not measured
    assert track.consistency.diverged and "dead reckoning" in track.consistency.reason


def _scenario(seed: int, traj: PlanarTrajectory = LINE):
    rng = np.random.default_rng(seed)
    model = UwbErrorModel()
    bias = draw_bias(4, model, rng)
    cal = RangeCalibration.fit(*calibration_campaign(model, bias, rng))
    t, _, ai = ranging_schedule(traj.duration, 60.0, 4)
    t, ai = t[:, 0, :], ai[:, 0, :]
    truth = traj.sample(t.ravel()).p.reshape(*t.shape, 3)
    sim = simulate_ranges(PAPER_ANCHORS_3D, truth, model, rng, bias=bias)
    y = cal.apply(np.einsum("rjj->rj", sim.ranges))
    nlos = np.einsum("rjj->rj", sim.nlos)
    imu = simulate_imu(traj, 100.0, ImuErrorModel(), rng)
    return model, t, ai, y, nlos, imu


def test_eskf_beats_ls_by_40_percent_with_outliers() -> None:
    model, t, ai, y, nlos, imu = _scenario(2)
    assert nlos.sum() > 20
    rej = reject_outliers(y, model.sigma(y))
    t_round = t.mean(axis=1)
    p_round = LINE.sample(t_round).p
    ls = locate(PAPER_ANCHORS_3D, rej.ranges, method="ls", sigma=model.sigma)
    ls_pe = np.mean(np.linalg.norm((ls.positions - p_round)[ls.valid][:, :2], axis=1))
    start = locate(PAPER_ANCHORS_3D, rej.ranges[:60], method="wls-t", sigma=model.sigma)
    p0 = np.nanmedian(start.positions, axis=0)
    yaw0 = LINE.sample(np.zeros(1)).yaw[0] + np.radians(5.0)
    f = Eskf(p0, np.zeros(3), initial_attitude(imu.accel[:100], yaw0), default_covariance())
    track = run_eskf(
        f,
        imu.t,
        imu.accel,
        imu.gyro,
        t.ravel(),
        ai.ravel(),
        y.ravel(),
        PAPER_ANCHORS_3D,
        model.sigma,
    )
    sel = imu.t > 1.0
    truth = LINE.sample(imu.t).p
    eskf_pe = np.mean(np.linalg.norm((track.p - truth)[sel][:, :2], axis=1))
    assert eskf_pe < 0.6 * ls_pe
    # the gate caught the NLOS ranges (they were not pre-rejected for the ESKF)
    assert track.n_rejected >= 0.8 * nlos.sum()
    assert track.n_covariance_repairs == 0
    P = track.P_final
    np.testing.assert_allclose(P, P.T)
    assert np.linalg.eigvalsh(P).min() > 0
    # position covariance is consistent with the actual error (loosely: 3 sigma)
    z = np.abs(track.p - truth)[sel] / np.sqrt(track.P_diag[sel][:, 0:3])
    assert np.mean(z < 3.0) > 0.95
    C = pose_covariance_world(track.q[-1], P)
    assert C.shape == (6, 6) and np.all(np.linalg.eigvalsh(C) > 0)


def _track(scenario, y=None, gyro_offset=(0.0, 0.0, 0.0)):
    model, t, ai, y0, _, imu = scenario
    start = locate(PAPER_ANCHORS_3D, y0[:60], method="wls-t", sigma=model.sigma)
    p0 = np.nanmedian(start.positions, axis=0)
    yaw0 = LINE.sample(np.zeros(1)).yaw[0]
    f = Eskf(p0, np.zeros(3), initial_attitude(imu.accel[:100], yaw0), default_covariance())
    return run_eskf(
        f,
        imu.t,
        imu.accel,
        imu.gyro + np.asarray(gyro_offset),
        t.ravel(),
        ai.ravel(),
        (y0 if y is None else y).ravel(),
        PAPER_ANCHORS_3D,
        model.sigma,
    )


@pytest.fixture(scope="module")
def clean_run():
    scenario = _scenario(5)
    return scenario, _track(scenario)


def test_consistent_run_has_nis_near_one_and_passes(clean_run) -> None:
    _, track = clean_run
    assert track.range_nis.shape == track.range_t.shape == track.range_gated.shape
    assert track.range_gated.sum() == track.n_rejected
    assert np.all(np.diff(track.range_t) >= 0)
    c = track.consistency
    assert c.n_updates + c.n_gated == track.range_t.size
    assert 0.8 < c.nis_mean < 1.15  # truncated chi-square(1): 0.97
    assert 0.7 < c.nis_mean_window < c.nis_threshold_window < 1.3
    assert c.n_updates_window > 400 and c.gated_share_window < 0.1
    assert not c.diverged and c.reason == ""
    assert c.rest is not None and c.rest.at_rest and c.rest.passed  # LINE ends standing
    assert c.bias.passed
    integrity = eskf_integrity(c)
    assert integrity.status == "ok" and integrity.global_test["passed"]
    pl = integrity.protection_level
    assert 0 < pl["horizontal"] < 1.0 and 0 < pl["vertical"] < 1.0


def test_anchor_bias_is_predicted_and_found(clean_run) -> None:
    scenario, track = clean_run
    _, t, ai, y, _, _ = scenario
    t_end = track.t[-1]
    b = track.consistency.bias
    onset = t_end - 2.0  # on the grid of hypothesized onsets
    k = int(np.flatnonzero((b.anchor == 2) & np.isclose(b.onset, onset))[0])
    biased = y + 0.15 * ((ai == 2) & (t >= onset))
    faulty = _track(scenario, biased)
    # the linearized filter predicts what the bias does to the final position
    moved = faulty.p[-1] - track.p[-1]
    predicted = 0.15 * b.sensitivity[:3, k]
    assert np.linalg.norm(moved - predicted) < 0.2 * np.linalg.norm(predicted)
    integrity = eskf_integrity(faulty.consistency, ["A1", "A2", "A3", "A4"], t_end=t_end)
    assert integrity.status == "failed"
    assert integrity.w_test["suspect"].startswith("anchor A3")
    assert "A3" in integrity.reason


def test_gyro_fault_at_rest_fails(clean_run) -> None:
    scenario, _ = clean_run
    faulty = _track(scenario, gyro_offset=(0.0, 0.0, 0.05))
    c = faulty.consistency
    assert c.diverged and "gyro" in c.reason
    assert c.rest is not None and c.rest.residual[2] > 0.03


def test_consistency_rules() -> None:
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 10.0, 2400)
    nis = rng.chisquare(1, t.size)
    none = BiasMonitor(4, np.zeros(1)).tests()
    ok = consistency(10.0, t, nis, nis > 8.81, none)
    assert not ok.diverged and 0.9 < ok.nis_mean < 1.05
    # an over-confident filter: innovations twice their predicted variance
    big = consistency(10.0, t, 2 * nis, 2 * nis > 8.81, none)
    assert big.diverged and "mean NIS" in big.reason and big.p_value_window < 1e-3
    # most ranges of the last seconds rejected
    gated = (nis > 8.81) | (t > 8.5)
    assert "gate rejected" in consistency(10.0, t, nis, gated, none).reason
    # the ranges stop 5 s before the pose
    late = consistency(15.0, t, nis, nis > 8.81, none)
    assert late.diverged and "dead reckoning" in late.reason
    record = eskf_integrity(late)
    assert record.status == "failed" and record.to_dict()["global_test"]["threshold"] is None


def test_run_eskf_refuses_impossible_imu_and_foreign_ranges() -> None:
    t = np.arange(200) * 0.01
    acc = np.tile([0.0, 0.0, 9.81], (200, 1))
    gyr = np.zeros((200, 3))

    def run(t=t, acc=acc, gyr=gyr, rt=None):
        rt = np.array([1.0]) if rt is None else rt
        f = Eskf(np.ones(3), np.zeros(3), np.array([1.0, 0, 0, 0]), default_covariance())
        n = rt.size
        return run_eskf(
            f, t, acc, gyr, rt, np.zeros(n, int), np.full(n, 3.0), PAPER_ANCHORS_3D, 0.05
        )

    assert run().range_t.size == 1
    with pytest.raises(InputError, match="IMU sample 5: specific force"):
        run(acc=np.where(np.arange(200)[:, None] == 5, 1e308, acc))
    with pytest.raises(InputError, match="IMU sample 7: a value is not finite"):
        run(gyr=np.where(np.arange(200)[:, None] == 7, np.nan, gyr))
    with pytest.raises(InputError, match="IMU sample 100: gap of 1e\\+09 s"):
        run(t=np.where(np.arange(200) >= 100, t + 1e9, t))
    with pytest.raises(InputError, match="does not cover the ranges"):
        run(rt=np.array([1.0, 30.0]))


def test_gating_rejects_an_outlier_and_keeps_the_state() -> None:
    q0 = quat_from_rotvec(np.zeros(3))
    p = np.array([2.0, 2.0, 2.0])
    P = default_covariance(sigma_p=0.02)
    f = Eskf(p, np.zeros(3), q0, P)
    a = PAPER_ANCHORS_3D[0]
    d = np.linalg.norm(p - a)
    nis = f.update_range(a, d + 1.0, 0.05)
    assert nis > f.params.gate and f.n_rejected == 1 and f.n_updates == 0
    np.testing.assert_array_equal(f.p, p)
    f.update_range(a, d + 0.03, 0.05)
    assert f.n_updates == 1 and np.linalg.norm(f.p - p) > 0
    ungated = Eskf(p, np.zeros(3), q0, P, EskfParams(gate=np.inf))
    ungated.update_range(a, d + 1.0, 0.05)
    assert ungated.n_rejected == 0 and np.linalg.norm(ungated.p - p) > 0.01


def test_height_update_and_input_checks() -> None:
    f = Eskf(np.array([1.0, 1.0, 2.3]), np.zeros(3), np.array([1.0, 0, 0, 0]), default_covariance())
    f.update_height(2.0, 0.01)
    assert abs(f.p[2] - 2.0) < 0.01
    with pytest.raises(InputError, match="15x15"):
        Eskf(np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0]), np.eye(6))
    with pytest.raises(InputError, match="strictly increasing"):
        run_eskf(
            f,
            np.array([0.0, 0.0]),
            np.zeros((2, 3)),
            np.zeros((2, 3)),
            np.zeros(0),
            np.zeros(0, int),
            np.zeros(0),
            PAPER_ANCHORS_3D,
            0.05,
        )


def test_initial_attitude_from_gravity() -> None:
    rv = np.array([0.05, -0.03, 0.8])
    R = exp_so3(rv)
    f_body = R.T @ np.array([0.0, 0.0, 9.81])
    q = initial_attitude(np.tile(f_body, (10, 1)), 0.0)
    R0 = matrix_from_quat(q)
    np.testing.assert_allclose(R0.T @ [0, 0, 1.0], R.T @ [0, 0, 1.0], atol=1e-9)


def test_cv_ekf_baseline_runs_and_gates() -> None:
    model, t, ai, y, nlos, _ = _scenario(3)
    part = t < 6.0  # the start of the run keeps the (filterpy, per-range) test fast
    times, pos, n_rej = cv_ekf_track(
        t[part], ai[part], y[part], PAPER_ANCHORS_3D, model.sigma, p0=LINE.sample(np.zeros(1)).p[0]
    )
    truth = LINE.sample(times).p
    pe = np.mean(np.linalg.norm((pos - truth)[times > 1.0][:, :2], axis=1))
    assert pe < 0.08
    assert n_rej >= 0.5 * nlos[part].sum()


def test_imu_simulator_at_rest_measures_gravity() -> None:
    rng = np.random.default_rng(4)
    imu = simulate_imu(LINE, 100.0, ImuErrorModel(), rng, duration=1.5)
    f = imu.accel - imu.accel_bias
    np.testing.assert_allclose(f.mean(axis=0), [0, 0, 9.81], atol=0.01)
    assert abs(np.std(f[:, 0]) - 0.004 * 10) < 0.01
    np.testing.assert_allclose((imu.gyro - imu.gyro_bias).mean(axis=0), 0, atol=0.002)
