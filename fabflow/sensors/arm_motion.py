"""Simulated sensor streams of an excavator arm (paper 000): end-effector and turn joint.

:func:`end_effector_streams` moves the end-effector along a printing-like loop and
returns the true poses with two measurements of them: 100 Hz kinematics (locally
smooth, globally biased by a slowly varying error of about 2 cm, as base GNSS and
arm deflection give the paper's 2.23 cm RMSE) and 10 Hz ICP poses (white error of
5.8 mm and 0.3 deg, the paper's 0.58 cm RMSE).

:func:`turn_joint_streams` turns the cabin slowly and returns the true angle, the
0.92 deg tooth-counting encoder reading and the difference of two noisy, biased
gyros.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fabflow.positioning.turn_joint import ENCODER_RESOLUTION, quantize
from fabflow.transforms.se3 import make_T, perturb
from fabflow.transforms.so3 import exp_so3

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class EndEffectorStreams:
    """True end-effector poses and their kinematic and ICP measurements (world frame)."""

    t: FloatArray
    T_true: FloatArray
    T_kin: FloatArray
    t_icp: FloatArray
    T_icp: FloatArray


def end_effector_streams(
    rng: np.random.Generator,
    duration: float = 30.0,
    kin_rate_hz: float = 100.0,
    icp_rate_hz: float = 10.0,
    kin_bias: float = 0.02,
    icp_sigma: float = 0.0058,
    icp_sigma_deg: float = 0.3,
) -> EndEffectorStreams:
    """Simulate the streams of an end-effector moving at about 0.4 m/s.

    Parameters
    ----------
    rng
        All noise and bias phases.
    duration
        Seconds simulated.
    kin_rate_hz, icp_rate_hz
        Rates of the kinematic and ICP poses.
    kin_bias
        Amplitude of the slowly varying kinematic position error (metres).
    icp_sigma, icp_sigma_deg
        ICP position (metres) and rotation (degrees) error, per axis.
    """
    dt = 1.0 / kin_rate_hz
    t = np.arange(0.0, duration, dt)
    n = len(t)
    w = 2 * np.pi / 15.0
    pos = np.c_[
        2.0 + np.cos(w * t),
        1.0 + 0.8 * np.sin(w * t),
        1.2 + 0.1 * np.sin(2 * np.pi * t / 7.0),
    ]
    rotvec = np.c_[0.05 * np.sin(t), np.zeros(n), w * t + np.pi / 2]
    T_true = make_T(exp_so3(rotvec), pos)
    phase = rng.uniform(0, 2 * np.pi, 4)
    err_kin = np.zeros((n, 6))
    err_kin[:, 0] = kin_bias * np.sin(2 * np.pi * t / 11.0 + phase[0])
    err_kin[:, 1] = 0.75 * kin_bias * np.sin(2 * np.pi * t / 17.0 + phase[1])
    err_kin[:, 2] = 0.5 * kin_bias * np.sin(2 * np.pi * t / 9.0 + phase[2])
    err_kin[:, 5] = 0.003 * np.sin(2 * np.pi * t / 13.0 + phase[3])
    err_kin[:, :3] += rng.normal(0.0, 0.001, (n, 3))
    err_kin[:, 3:] += rng.normal(0.0, 0.0005, (n, 3))
    step = round(kin_rate_hz / icp_rate_hz)
    idx = np.arange(0, n, step)
    err_icp = np.c_[
        rng.normal(0.0, icp_sigma, (len(idx), 3)),
        rng.normal(0.0, np.radians(icp_sigma_deg), (len(idx), 3)),
    ]
    return EndEffectorStreams(
        t=t,
        T_true=T_true,
        T_kin=perturb(T_true, err_kin),
        t_icp=t[idx],
        T_icp=perturb(T_true[idx], err_icp),
    )


@dataclass(frozen=True, eq=False)
class TurnJointStreams:
    """True cabin turn angle, encoder readings and gyro-difference rates."""

    t: FloatArray
    angle: FloatArray
    encoder: FloatArray
    gyro_rate: FloatArray


def turn_joint_streams(
    rng: np.random.Generator,
    duration: float = 60.0,
    rate_hz: float = 100.0,
    gyro_sigma: float = 0.007,
    gyro_bias_sigma: float = 0.002,
) -> TurnJointStreams:
    """Simulate slow cabin turns (below 0.1 rad/s) measured by encoder and two gyros.

    Parameters
    ----------
    rng
        Noise and biases.
    duration
        Seconds simulated.
    rate_hz
        Sample rate of encoder and gyros.
    gyro_sigma
        White noise of each gyro (rad/s per sample).
    gyro_bias_sigma
        Standard deviation of each gyro's constant bias (rad/s).
    """
    t = np.arange(0.0, duration, 1.0 / rate_hz)
    angle = 0.3 * np.sin(2 * np.pi * t / 40.0) + 0.1 * np.sin(2 * np.pi * t / 13.0)
    rate = 0.3 * 2 * np.pi / 40.0 * np.cos(2 * np.pi * t / 40.0) + 0.1 * 2 * np.pi / 13.0 * np.cos(
        2 * np.pi * t / 13.0
    )
    b_cabin, b_chassis = rng.normal(0.0, gyro_bias_sigma, 2)
    cabin = rate + b_cabin + rng.normal(0.0, gyro_sigma, len(t))
    chassis = b_chassis + rng.normal(0.0, gyro_sigma, len(t))
    return TurnJointStreams(
        t=t, angle=angle, encoder=quantize(angle, ENCODER_RESOLUTION), gyro_rate=cabin - chassis
    )
