"""A constant-velocity EKF over UWB ranges: the baseline the UWB/IMU ESKF is measured against.

filterpy's ``ExtendedKalmanFilter`` with a constant-velocity model, the same
per-range updates and the same Mahalanobis gating as
:mod:`fabflow.positioning.eskf`, but no IMU.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fabflow.positioning.eskf import CHI2_1DOF_997


def cv_ekf_track(
    range_t: np.ndarray,
    anchor_index: np.ndarray,
    ranges: np.ndarray,
    anchors: np.ndarray,
    sigma: float | Callable[[np.ndarray], np.ndarray],
    p0: np.ndarray,
    accel_psd: float = 0.5,
    gate: float = CHI2_1DOF_997,
    sigma_p0: float = 0.2,
    sigma_v0: float = 0.1,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Constant-velocity EKF on per-range updates (filterpy), the baseline without IMU.

    Parameters
    ----------
    range_t, anchor_index, ranges
        (K,) timestamps (s), anchor indices and calibrated ranges (m); NaN skipped.
    anchors
        (n_anchors, 3) anchors (m).
    sigma
        Range noise standard deviation (m), constant or a function of the range.
    p0
        Initial position (m).
    accel_psd
        White acceleration power spectral density of the motion model (m^2/s^3).
    gate
        Mahalanobis gate (chi-square, 1 degree of freedom).
    sigma_p0, sigma_v0
        Initial standard deviations of position (m) and velocity (m/s).

    Returns
    -------
    t
        (K',) times of the accepted-or-tested ranges (s).
    positions
        (K', 3) position after each range.
    n_rejected
        Ranges rejected by the gate.
    """
    from filterpy.common import Q_continuous_white_noise
    from filterpy.kalman import ExtendedKalmanFilter

    order = np.argsort(range_t, kind="stable")
    rt = np.asarray(range_t, dtype=float)[order]
    ai = np.asarray(anchor_index)[order]
    rv = np.asarray(ranges, dtype=float)[order]
    keep = np.isfinite(rv)
    rt, ai, rv = rt[keep], ai[keep], rv[keep]
    rs = np.asarray(sigma(rv), dtype=float) if callable(sigma) else np.full(rv.shape, sigma)
    A = np.asarray(anchors, dtype=float)
    ekf = ExtendedKalmanFilter(dim_x=6, dim_z=1)
    ekf.x = np.concatenate([np.asarray(p0, dtype=float), np.zeros(3)])
    ekf.P = np.diag([sigma_p0**2] * 3 + [sigma_v0**2] * 3)
    out = np.empty((rt.size, 3))
    n_rejected = 0
    t_prev = rt[0] if rt.size else 0.0
    for k in range(rt.size):
        dt = rt[k] - t_prev
        t_prev = rt[k]
        if dt > 0:
            F = np.eye(6)
            F[0:3, 3:6] = np.eye(3) * dt
            ekf.F = F
            ekf.Q = Q_continuous_white_noise(
                dim=2, dt=dt, spectral_density=accel_psd, block_size=3, order_by_dim=False
            )
            ekf.predict()
        a = A[ai[k]]

        def hx(x: np.ndarray, a: np.ndarray = a) -> np.ndarray:
            return np.array([np.linalg.norm(x[:3] - a)])

        def jac(x: np.ndarray, a: np.ndarray = a) -> np.ndarray:
            d = x[:3] - a
            H = np.zeros((1, 6))
            H[0, :3] = d / max(np.linalg.norm(d), 1e-9)
            return H

        H = jac(ekf.x)
        y = rv[k] - hx(ekf.x)[0]
        S = float((H @ ekf.P @ H.T)[0, 0]) + rs[k] ** 2
        if y * y / S > gate:
            n_rejected += 1
        else:
            ekf.update(np.array([rv[k]]), jac, hx, R=rs[k] ** 2)
        out[k] = ekf.x[:3]
    return rt, out, n_rejected
