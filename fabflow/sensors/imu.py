"""IMU simulator: specific force and angular rate with white noise and bias random walk.

The body frame is the platform frame (x forward, z up); the world z axis is up
and gravity is ``(0, 0, -g)``. The accelerometer measures the specific force
``R^T (a - g_vec)``, the gyro the body angular rate. Noise is given as
continuous densities, so any sample rate gives consistent statistics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fabflow.positioning.eskf import GRAVITY
from fabflow.sensors.uwb_trajectories import PlanarTrajectory


@dataclass(frozen=True)
class ImuErrorModel:
    """Noise of a consumer MEMS IMU (defaults), as continuous-time densities.

    Attributes
    ----------
    accel_noise
        Accelerometer white noise density (m/s^2/sqrt(Hz)).
    gyro_noise
        Gyro white noise density (rad/s/sqrt(Hz)).
    accel_bias_walk
        Accelerometer bias random walk (m/s^3/sqrt(Hz)).
    gyro_bias_walk
        Gyro bias random walk (rad/s^2/sqrt(Hz)).
    accel_bias_sigma
        Standard deviation of the initial accelerometer bias per axis (m/s^2).
    gyro_bias_sigma
        Standard deviation of the initial gyro bias per axis (rad/s).
    """

    accel_noise: float = 0.004
    gyro_noise: float = 0.0005
    accel_bias_walk: float = 2e-4
    gyro_bias_walk: float = 2e-5
    accel_bias_sigma: float = 0.05
    gyro_bias_sigma: float = 0.003


@dataclass(frozen=True)
class ImuData:
    """Simulated IMU samples.

    Attributes
    ----------
    t
        (N,) sample times (s).
    accel
        (N, 3) specific force in the body frame (m/s^2).
    gyro
        (N, 3) angular rate in the body frame (rad/s).
    accel_bias, gyro_bias
        (N, 3) the true biases (for evaluation).
    """

    t: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray
    accel_bias: np.ndarray
    gyro_bias: np.ndarray


def simulate_imu(
    trajectory: PlanarTrajectory,
    rate_hz: float,
    model: ImuErrorModel,
    rng: np.random.Generator,
    duration: float | None = None,
) -> ImuData:
    """Simulate IMU samples along a trajectory.

    Parameters
    ----------
    trajectory
        The body trajectory (position, acceleration, heading, heading rate).
    rate_hz
        IMU sample rate (Hz).
    model
        Noise model.
    rng
        Random generator.
    duration
        Length of the record (s); the trajectory's duration by default.
    """
    duration = trajectory.duration if duration is None else duration
    dt = 1.0 / rate_hz
    t = np.arange(int(np.floor(duration * rate_hz)) + 1) * dt
    truth = trajectory.sample(t)
    n = t.size
    g_vec = np.array([0.0, 0.0, -GRAVITY])
    f_world = truth.a - g_vec
    R = truth.R_world_body
    f_body = np.einsum("nji,nj->ni", R, f_world)
    w_body = np.zeros((n, 3))
    w_body[:, 2] = truth.yaw_rate
    ba0 = model.accel_bias_sigma * rng.standard_normal(3)
    bg0 = model.gyro_bias_sigma * rng.standard_normal(3)
    ba = ba0 + np.cumsum(model.accel_bias_walk * np.sqrt(dt) * rng.standard_normal((n, 3)), axis=0)
    bg = bg0 + np.cumsum(model.gyro_bias_walk * np.sqrt(dt) * rng.standard_normal((n, 3)), axis=0)
    accel = f_body + ba + model.accel_noise / np.sqrt(dt) * rng.standard_normal((n, 3))
    gyro = w_body + bg + model.gyro_noise / np.sqrt(dt) * rng.standard_normal((n, 3))
    return ImuData(t=t, accel=accel, gyro=gyro, accel_bias=ba, gyro_bias=bg)
