"""EKF fusion of ICP and kinematics; turn-joint KF against the complementary filter."""

from __future__ import annotations

import numpy as np
import pytest

from fabflow.errors import InputError
from fabflow.positioning.icp_fusion import fuse_icp_kinematics
from fabflow.positioning.turn_joint import (
    ENCODER_RESOLUTION,
    TurnJointKF,
    complementary_filter,
    quantize,
)
from fabflow.sensors.arm_motion import end_effector_streams, turn_joint_streams
from fabflow.transforms.se3 import pose_error


def position_rmse(T_est: np.ndarray, T_true: np.ndarray, skip: int = 100) -> float:
    e = pose_error(T_est, T_true)[skip:, :3]
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def test_ekf_beats_icp_alone_and_kinematics_alone() -> None:
    s = end_effector_streams(np.random.default_rng(0), duration=6.0)
    fused = fuse_icp_kinematics(s.t, s.T_kin, s.t_icp, s.T_icp)
    assert fused.T_world_ee.shape == (len(s.t), 4, 4)
    hold = s.T_icp[np.searchsorted(s.t_icp, s.t, side="right") - 1]  # ICP at 100 Hz
    ekf, icp_only, kin = (
        position_rmse(fused.T_world_ee, s.T_true),
        position_rmse(hold, s.T_true),
        position_rmse(s.T_kin, s.T_true),
    )
    assert ekf < 0.7 * icp_only and ekf < 0.7 * kin, (ekf, icp_only, kin)
    sd = np.sqrt(np.einsum("nii->ni", fused.covariance)[100:, :3])
    assert np.all(sd > 0) and np.median(sd) < 0.02
    speed = np.linalg.norm(fused.twist[100:, :3], axis=1)
    assert 0.2 < np.median(speed) < 0.6  # the loop runs at about 0.4 m/s


def test_fusion_input_checks() -> None:
    s = end_effector_streams(np.random.default_rng(1), duration=0.5)
    with pytest.raises(InputError):
        fuse_icp_kinematics(s.t[::-1], s.T_kin, s.t_icp, s.T_icp)
    with pytest.raises(InputError):
        fuse_icp_kinematics(s.t, s.T_kin[:, :3], s.t_icp, s.T_icp)


def test_quantize_reads_whole_teeth() -> None:
    assert np.degrees(ENCODER_RESOLUTION) == pytest.approx(0.918, abs=1e-3)
    q = quantize(np.array([0.0, 0.5, 1.0, -0.5]) * ENCODER_RESOLUTION)
    np.testing.assert_allclose(q / ENCODER_RESOLUTION, [0, 0, 1, -1])


def test_turn_joint_kf_beats_the_complementary_filter() -> None:
    s = turn_joint_streams(np.random.default_rng(2), duration=20.0)
    kf, rate = TurnJointKF().run(s.t, s.encoder, s.gyro_rate)
    cf = complementary_filter(s.t, s.encoder, s.gyro_rate, alpha=0.98)
    e_kf = np.mean(np.abs(kf - s.angle))
    e_cf = np.mean(np.abs(cf - s.angle))
    assert e_kf < 0.0025 and e_cf > 3 * e_kf, (e_kf, e_cf)
    assert e_kf < ENCODER_RESOLUTION / 4  # better than the encoder's own resolution
    true_rate = np.gradient(s.angle, s.t)
    assert np.mean(np.abs(rate - true_rate)) < 0.01


def test_turn_joint_kf_handles_missing_encoder_samples() -> None:
    s = turn_joint_streams(np.random.default_rng(3), duration=5.0)
    enc = s.encoder.copy()
    enc[1::2] = np.nan  # encoder at half the gyro rate
    kf, _ = TurnJointKF().run(s.t, enc, s.gyro_rate)
    assert np.mean(np.abs(kf - s.angle)) < 0.004
    with pytest.raises(InputError):
        TurnJointKF().run(s.t, enc[:-1], s.gyro_rate)
    with pytest.raises(InputError):
        complementary_filter(s.t, s.encoder, s.gyro_rate, alpha=1.5)
