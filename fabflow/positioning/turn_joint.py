"""Low-resolution turn joint estimation (paper 000, section III-A, eqs 1-3).

The cabin turn joint of the excavator is measured by counting gear teeth: 98 teeth
give an angle resolution of only 0.92 deg. Its rate is the difference of the
cabin and chassis gyros. :class:`TurnJointKF` fuses both in a discrete Kalman
filter over ``x = [psi, psi_dot]`` (plus the gyro-difference bias) with a
constant-velocity model (eq 2) and the observation
``z = [psi_encoder, omega_cabin - omega_chassis]`` (eq 3); the encoder's
quantization enters as its uniform-error variance ``q^2 / 12``.
:func:`complementary_filter` is the baseline it replaces: the gyro rate
integrated and pulled towards the encoder angle with a fixed weight.

All angles in radians, rates in rad/s, times in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError

FloatArray = NDArray[np.float64]

ENCODER_RESOLUTION = np.radians(360.0 / 98.0 / 4.0)
"""0.92 deg: 98 gear teeth read by two inductive sensors in quadrature (paper 000)."""


def quantize(angle: ArrayLike, resolution: float = ENCODER_RESOLUTION) -> FloatArray:
    """What a tooth-counting encoder reads: the angle floored to its resolution (radians)."""
    return np.floor(np.asarray(angle, dtype=float) / resolution) * resolution


@dataclass
class TurnJointKF:
    """Kalman filter of the turn joint angle and rate (and the gyro-difference bias).

    The paper's state ``[psi, psi_dot]`` is extended by the constant bias ``b`` of
    the gyro difference (``z_gyro = psi_dot + b``), which the encoder makes
    observable; without it a biased rate drags the angle between encoder steps.

    Attributes
    ----------
    resolution
        Encoder resolution (radians); its quantization error is modelled as uniform.
    gyro_sigma
        Standard deviation of the gyro-difference rate (rad/s, per sample).
    accel_sigma
        Process noise: white angular acceleration (rad/s^2).
    bias_sigma
        Prior standard deviation of the gyro-difference bias (rad/s).
    bias_walk
        Random walk of the bias (rad/s per sqrt(s)).
    """

    resolution: float = ENCODER_RESOLUTION
    gyro_sigma: float = 0.01
    accel_sigma: float = 0.2
    bias_sigma: float = 0.005
    bias_walk: float = 1e-4

    def run(
        self,
        t: ArrayLike,
        encoder: ArrayLike,
        gyro_rate: ArrayLike,
    ) -> tuple[FloatArray, FloatArray]:
        """Filter a sequence of encoder angles and gyro-difference rates.

        Parameters
        ----------
        t
            ``(n,)`` increasing sample times (seconds).
        encoder
            ``(n,)`` encoder angles (radians, quantized); NaN where no reading.
        gyro_rate
            ``(n,)`` cabin minus chassis angular rate about the joint axis (rad/s).

        Returns
        -------
        angle, rate
            ``(n,)`` filtered angle (radians) and rate (rad/s). The encoder reads the
            floor of the angle, so half a resolution step is added to its readings.
        """
        t = np.asarray(t, dtype=float)
        enc = np.asarray(encoder, dtype=float)
        gyr = np.asarray(gyro_rate, dtype=float)
        if not (t.shape == enc.shape == gyr.shape) or t.ndim != 1 or len(t) == 0:
            raise InputError("t, encoder and gyro_rate must be 1-D arrays of the same length")
        if np.any(np.diff(t) <= 0):
            raise InputError("sample times must increase")
        first = enc[np.flatnonzero(np.isfinite(enc))[0]] if np.isfinite(enc).any() else 0.0
        x, P = self.start(first, gyr[0])
        out = np.empty((len(t), 2))
        prev = t[0]
        for k in range(len(t)):  # a recursive filter: one step per sample
            x, P = self.step(x, P, t[k] - prev, enc[k], gyr[k])
            prev = t[k]
            out[k] = x[:2]
        return out[:, 0], out[:, 1]

    def start(self, encoder: float, gyro_rate: float) -> tuple[FloatArray, FloatArray]:
        """The state ``[psi, psi_dot, b]`` and its covariance before the first sample.

        Parameters
        ----------
        encoder
            First encoder reading (radians, the floor of the angle).
        gyro_rate
            First gyro-difference rate (rad/s).
        """
        r_gyr = self.gyro_sigma**2
        x = np.array([encoder + 0.5 * self.resolution, gyro_rate, 0.0])
        P = np.diag([self.resolution**2, r_gyr + self.bias_sigma**2, self.bias_sigma**2])
        return x, P

    def step(
        self, x: FloatArray, P: FloatArray, dt: float, encoder: float, gyro_rate: float
    ) -> tuple[FloatArray, FloatArray]:
        """One filter step: predict over ``dt`` seconds, then update with one sample.

        Parameters
        ----------
        x, P
            State ``[psi, psi_dot, b]`` (rad, rad/s, rad/s) and its covariance.
        dt
            Time since the previous sample (s; 0 for the first).
        encoder
            Encoder reading (radians, the floor of the angle; NaN: none).
        gyro_rate
            Gyro-difference rate (rad/s).

        Returns
        -------
        x, P
            The updated state and covariance.
        """
        F, Q = _transition(dt, self.accel_sigma, self.bias_walk)
        x = F @ x
        P = F @ P @ F.T + Q
        if np.isfinite(encoder):
            z = np.array([encoder + 0.5 * self.resolution, gyro_rate])
            H, R = _BOTH, np.diag([self.resolution**2 / 12.0, self.gyro_sigma**2])
        else:
            z = np.array([gyro_rate])
            H, R = _GYRO, np.array([[self.gyro_sigma**2]])
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        return x + K @ (z - H @ x), (np.eye(3) - K @ H) @ P


_BOTH = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]])
"""Observation of ``[psi, psi_dot, b]`` by the encoder and the gyro difference (eq. 3)."""
_GYRO = _BOTH[1:]


@lru_cache(maxsize=64)
def _transition(dt: float, accel_sigma: float, bias_walk: float) -> tuple[FloatArray, FloatArray]:
    """Transition ``F`` and process noise ``Q`` of the constant-velocity model over ``dt``."""
    F = np.array([[1.0, dt, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    q = accel_sigma**2
    Q = np.zeros((3, 3))
    Q[:2, :2] = q * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
    Q[2, 2] = bias_walk**2 * dt
    F.flags.writeable = Q.flags.writeable = False
    return F, Q


def complementary_filter(
    t: ArrayLike, encoder: ArrayLike, gyro_rate: ArrayLike, alpha: float = 0.98
) -> FloatArray:
    """The baseline: ``psi_k = alpha (psi_{k-1} + omega dt) + (1 - alpha) psi_encoder``.

    Parameters
    ----------
    t, encoder, gyro_rate
        As for :meth:`TurnJointKF.run` (NaN encoder samples keep the integrated value).
    alpha
        Weight of the integrated gyro (0..1).

    Returns
    -------
    numpy.ndarray
        ``(n,)`` estimated angle (radians).
    """
    t = np.asarray(t, dtype=float)
    enc = np.asarray(encoder, dtype=float)
    gyr = np.asarray(gyro_rate, dtype=float)
    if not 0.0 <= alpha <= 1.0:
        raise InputError(f"alpha must be in [0, 1], got {alpha}")
    out = np.empty(len(t))
    psi = enc[0] if np.isfinite(enc[0]) else 0.0
    prev = t[0]
    for k in range(len(t)):  # a recursive filter: one step per sample
        psi = psi + gyr[k] * (t[k] - prev)
        prev = t[k]
        if np.isfinite(enc[k]):
            psi = alpha * psi + (1.0 - alpha) * enc[k]
        out[k] = psi
    return out
