"""UWB/IMU fusion: an error-state Kalman filter, and a constant-velocity EKF baseline.

The ESKF follows seeds/003 equations 19-28 and Sola, "Quaternion kinematics for
the error-state Kalman filter" (2017), sections 5.3-6.3 (local attitude error):

* nominal state ``x = [p, v, q, a_b, w_b]``: position and velocity in the world
  (metres, m/s), attitude quaternion ``q`` = (w, x, y, z) of the body in the
  world, accelerometer and gyro biases (body frame);
* error state ``dx = [dp, dv, dtheta, da_b, dw_b]`` (15), with the true
  attitude ``q_t = q (x) q{dtheta}`` (dtheta in the body frame);
* IMU propagation at every IMU sample (equations 20-21), the IMU reading held
  between samples; the nominal state is integrated to each range's own
  timestamp (no resampling), the error covariance once per IMU interval (its
  change within 10 ms is negligible against the range noise);
* every UWB range is its own scalar measurement ``|p + R l - a_i|`` (tightly
  coupled, equations 22-24), gated by its Mahalanobis distance (NLOS
  rejection), applied with the Joseph form so the covariance stays symmetric
  positive definite; injection and reset (equations 25-28) with
  ``G = blockdiag(I, I, I - [dtheta/2]x, I, I)``.

The world z axis is up; gravity is ``(0, 0, -g)``.

:func:`cv_ekf_track` is the baseline without IMU: filterpy's
``ExtendedKalmanFilter`` with a constant-velocity model and the same per-range
updates and gating.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fabflow.errors import InputError
from fabflow.transforms.so3 import matrix_from_quat, quat_from_matrix

GRAVITY = 9.81
CHI2_1DOF_997 = 8.81
"""Chi-square quantile (1 degree of freedom, 99.7 %): the default range gate."""


@dataclass(frozen=True)
class EskfParams:
    """Noise and gating settings of the ESKF.

    Attributes
    ----------
    accel_noise, gyro_noise
        White noise densities (m/s^2/sqrt(Hz), rad/s/sqrt(Hz)).
    accel_bias_walk, gyro_bias_walk
        Bias random walk densities (m/s^3/sqrt(Hz), rad/s^2/sqrt(Hz)).
    gate
        Mahalanobis gate on the squared normalized innovation of one range
        (chi-square, 1 degree of freedom); ``inf`` disables gating.
    lever_arm
        Tag position in the body (IMU) frame (metres).
    gravity
        Magnitude of gravity (m/s^2).
    """

    accel_noise: float = 0.004
    gyro_noise: float = 0.0005
    accel_bias_walk: float = 2e-4
    gyro_bias_walk: float = 2e-5
    gate: float = CHI2_1DOF_997
    lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gravity: float = GRAVITY


def _quat_to_R(q: np.ndarray) -> np.ndarray:
    # Hot-loop version of transforms.so3.matrix_from_quat for one unit quaternion
    # (the library function validates and broadcasts, ~100x slower per call).
    w, x, y, z = q.tolist()
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _quat_rotate_right(q: np.ndarray, th: np.ndarray) -> np.ndarray:
    # q (x) q{th}, renormalized; hot-loop version of the library's rotvec/quaternion maths.
    tx, ty, tz = th.tolist()
    a = math.sqrt(tx * tx + ty * ty + tz * tz)
    if a < 1e-12:
        c, s = 1.0, 0.5
    else:
        c, s = math.cos(0.5 * a), math.sin(0.5 * a) / a
    bw, bx, by, bz = c, s * tx, s * ty, s * tz
    w, x, y, z = q.tolist()
    ow = w * bw - x * bx - y * by - z * bz
    ox = w * bx + x * bw + y * bz - z * by
    oy = w * by - x * bz + y * bw + z * bx
    oz = w * bz + x * by - y * bx + z * bw
    n = math.sqrt(ow * ow + ox * ox + oy * oy + oz * oz)
    return np.array([ow / n, ox / n, oy / n, oz / n])


def _exp_transpose(th: np.ndarray) -> np.ndarray:
    # Exp(th)^T for one small rotation vector, via the hot-loop quaternion helpers.
    return _quat_to_R(_quat_rotate_right(_UNIT_QUAT, th)).T


_UNIT_QUAT = np.array([1.0, 0.0, 0.0, 0.0])


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


class Eskf:
    """Error-state Kalman filter for UWB ranges and an IMU (see the module docstring).

    Parameters
    ----------
    p, v
        Initial position (m) and velocity (m/s) in the world.
    q
        Initial attitude quaternion (w, x, y, z) of the body in the world.
    P
        15x15 initial error covariance over ``[dp, dv, dtheta, da_b, dw_b]``.
    params
        Noise and gating settings.
    accel_bias, gyro_bias
        Initial bias estimates (body frame).
    """

    def __init__(
        self,
        p: np.ndarray,
        v: np.ndarray,
        q: np.ndarray,
        P: np.ndarray,
        params: EskfParams | None = None,
        accel_bias: np.ndarray | None = None,
        gyro_bias: np.ndarray | None = None,
    ) -> None:
        self.params = params or EskfParams()
        self.p = np.array(p, dtype=float)
        self.v = np.array(v, dtype=float)
        q = np.asarray(q, dtype=float)
        self.q = q / np.linalg.norm(q)
        self.ab = np.zeros(3) if accel_bias is None else np.array(accel_bias, dtype=float)
        self.wb = np.zeros(3) if gyro_bias is None else np.array(gyro_bias, dtype=float)
        P = np.array(P, dtype=float)
        if P.shape != (15, 15):
            raise InputError(f"ESKF covariance must be 15x15, got {P.shape}")
        self.P = 0.5 * (P + P.T)
        self.R = _quat_to_R(self.q)
        self.g = np.array([0.0, 0.0, -self.params.gravity])
        self.lever = np.asarray(self.params.lever_arm, dtype=float)
        self.n_updates = 0
        self.n_rejected = 0
        self._F = np.eye(15)
        self._eye15 = np.eye(15)
        self._eye3 = np.eye(3)
        self._H = np.zeros(15)
        self._has_lever = bool(np.any(self.lever != 0.0))
        pr = self.params
        self._q_rate = np.concatenate(
            [
                np.zeros(3),
                np.full(3, pr.accel_noise**2),
                np.full(3, pr.gyro_noise**2),
                np.full(3, pr.accel_bias_walk**2),
                np.full(3, pr.gyro_bias_walk**2),
            ]
        )

    def propagate(self, accel: np.ndarray, gyro: np.ndarray, dt: float) -> None:
        """Integrate one IMU reading (body specific force, angular rate) over ``dt`` seconds."""
        if dt <= 0.0:
            return
        self.propagate_covariance(accel, gyro, dt)
        self.propagate_nominal(accel, gyro, dt)

    def propagate_nominal(self, accel: np.ndarray, gyro: np.ndarray, dt: float) -> None:
        """Integrate the nominal state only (equation 20, first line)."""
        if dt <= 0.0:
            return
        a_w = self.R @ (accel - self.ab) + self.g
        self.p = self.p + (self.v + (0.5 * dt) * a_w) * dt
        self.v = self.v + a_w * dt
        self.q = _quat_rotate_right(self.q, (gyro - self.wb) * dt)
        self.R = _quat_to_R(self.q)

    def propagate_covariance(self, accel: np.ndarray, gyro: np.ndarray, dt: float) -> None:
        """Propagate the error covariance over ``dt`` from the current nominal state (eq. 21)."""
        if dt <= 0.0:
            return
        R = self.R
        F = self._F
        F[0:3, 3:6] = self._eye3 * dt
        ax, ay, az = (accel - self.ab).tolist()
        # -R [a]x dt, written out (one small product instead of building the skew matrix)
        F[3:6, 6:9] = np.column_stack(
            (R[:, 1] * az - R[:, 2] * ay, R[:, 2] * ax - R[:, 0] * az, R[:, 0] * ay - R[:, 1] * ax)
        ) * (-dt)
        F[3:6, 9:12] = R * (-dt)
        F[6:9, 6:9] = _exp_transpose((gyro - self.wb) * dt)
        F[6:9, 12:15] = self._eye3 * (-dt)
        P = F @ self.P @ F.T
        P.ravel()[::16] += self._q_rate * dt
        self.P = P

    def _correct(self, H: np.ndarray, innovation: float, var: float) -> float:
        """Gate and apply one scalar measurement; returns the squared normalized innovation."""
        PHt = self.P @ H
        S = float(H @ PHt) + var
        nis = innovation * innovation / S
        if nis > self.params.gate:
            self.n_rejected += 1
            return nis
        K = PHt / S
        # P - K S K^T: equal to the Joseph form for the optimal gain; symmetrized here
        # and checked for positive definiteness in run_eskf.
        P = self.P - K[:, None] * PHt[None, :]
        dx = K * innovation
        self.p = self.p + dx[0:3]
        self.v = self.v + dx[3:6]
        dth = dx[6:9]
        self.q = _quat_rotate_right(self.q, dth)
        self.R = _quat_to_R(self.q)
        self.ab = self.ab + dx[9:12]
        self.wb = self.wb + dx[12:15]
        # reset (eq. 28): G = I except its attitude block I - [dtheta/2]x
        B = self._eye3 - _skew(0.5 * dth)
        P[6:9, :] = B @ P[6:9, :]
        P[:, 6:9] = P[:, 6:9] @ B.T
        self.P = 0.5 * (P + P.T)
        self.n_updates += 1
        return nis

    def ensure_positive_definite(self, floor: float = 1e-12) -> bool:
        """Symmetrize the covariance and, if it lost positive definiteness, clip its eigenvalues.

        Returns True when a repair was needed.
        """
        P = 0.5 * (self.P + self.P.T)
        try:
            np.linalg.cholesky(P)
            self.P = P
            return False
        except np.linalg.LinAlgError:
            w, V = np.linalg.eigh(P)
            self.P = (V * np.maximum(w, floor)) @ V.T
            return True

    def update_range(
        self, anchor: np.ndarray, measured: float, sigma: float, lever: np.ndarray | None = None
    ) -> float:
        """Apply one UWB range (metres) to ``anchor`` with noise ``sigma`` (metres).

        ``lever`` is the tag position in the body frame (``params.lever_arm`` when
        omitted). Returns the squared normalized innovation (the range was
        rejected when it exceeds ``params.gate``).
        """
        H = self._H
        H[:] = 0.0
        if lever is None:
            lever = self.lever
            has_lever = self._has_lever
        else:
            has_lever = True
        if has_lever:
            diff = self.p + self.R @ lever - anchor
        else:
            diff = self.p - anchor
        dist = math.sqrt(diff @ diff)
        u = diff / max(dist, 1e-9)
        H[0:3] = u
        if has_lever:
            w = self.R.T @ u
            lx, ly, lz = lever.tolist()
            H[6:9] = (ly * w[2] - lz * w[1], lz * w[0] - lx * w[2], lx * w[1] - ly * w[0])
        return self._correct(H, measured - dist, sigma * sigma)

    def update_height(self, z: float, sigma: float) -> float:
        """Apply a known height of the body origin (metres), e.g. a platform on a floor."""
        H = self._H
        H[:] = 0.0
        H[2] = 1.0
        return self._correct(H, z - self.p[2], sigma * sigma)


@dataclass(frozen=True)
class EskfTrack:
    """ESKF output sampled at the IMU times.

    Attributes
    ----------
    t
        (M,) times (s).
    p, v
        (M, 3) position (m) and velocity (m/s) of the body origin in the world.
    q
        (M, 4) attitude quaternions (w, x, y, z).
    accel_bias, gyro_bias
        (M, 3) bias estimates.
    P_diag
        (M, 15) diagonal of the error covariance.
    P_final
        15x15 error covariance at the end.
    n_updates, n_rejected
        Ranges applied and ranges rejected by the gate.
    n_covariance_repairs
        Times the covariance had lost positive definiteness and was repaired (checked
        every 100 IMU samples; expected 0).
    """

    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    accel_bias: np.ndarray
    gyro_bias: np.ndarray
    P_diag: np.ndarray
    P_final: np.ndarray
    n_updates: int
    n_rejected: int
    n_covariance_repairs: int = 0


def initial_attitude(accel_rest: np.ndarray, yaw: float) -> np.ndarray:
    """Attitude quaternion from the mean specific force at rest (roll, pitch) and a heading.

    Parameters
    ----------
    accel_rest
        (k, 3) accelerometer samples while the body stands still (m/s^2).
    yaw
        Heading about the world z axis (rad), from a prior (the IMU cannot observe it at rest).
    """
    f = np.mean(np.atleast_2d(accel_rest), axis=0)
    roll = math.atan2(f[1], f[2])
    pitch = math.atan2(-f[0], math.hypot(f[1], f[2]))
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    Ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
    Rx = np.array([[1.0, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return quat_from_matrix(Rz @ Ry @ Rx)


def default_covariance(
    sigma_p: float = 0.2,
    sigma_v: float = 0.05,
    sigma_tilt: float = math.radians(2.0),
    sigma_yaw: float = math.radians(10.0),
    sigma_ab: float = 0.1,
    sigma_wb: float = 0.005,
) -> np.ndarray:
    """A diagonal 15x15 initial error covariance (units: m, m/s, rad, m/s^2, rad/s)."""
    d = np.concatenate(
        [
            np.full(3, sigma_p**2),
            np.full(3, sigma_v**2),
            [sigma_tilt**2, sigma_tilt**2, sigma_yaw**2],
            np.full(3, sigma_ab**2),
            np.full(3, sigma_wb**2),
        ]
    )
    return np.diag(d)


def run_eskf(
    filt: Eskf,
    imu_t: np.ndarray,
    accel: np.ndarray,
    gyro: np.ndarray,
    range_t: np.ndarray,
    anchor_index: np.ndarray,
    ranges: np.ndarray,
    anchors: np.ndarray,
    sigma: float | Callable[[np.ndarray], np.ndarray],
    height: tuple[float, float] | None = None,
    tag_index: np.ndarray | None = None,
    lever_arms: np.ndarray | None = None,
) -> EskfTrack:
    """Run the filter over an IMU record and a stream of timestamped ranges.

    Each IMU sample is held until the next one; a range is applied at its own
    time after propagating to it. Output is recorded at every IMU sample time
    (after the ranges up to that time).

    Parameters
    ----------
    filt
        An initialized filter (state at ``imu_t[0]``).
    imu_t, accel, gyro
        (M,) sample times (s) and (M, 3) readings; times strictly increasing.
    range_t, anchor_index, ranges
        (K,) range timestamps (s), anchor indices and calibrated ranges (m); NaN
        ranges are skipped. Sorted by time here.
    anchors
        (n_anchors, 3) anchor positions in the world (m).
    sigma
        Range noise standard deviation (m), constant or a function of the range.
    height
        Optional ``(z, sigma)`` known height of the body origin, applied at every
        IMU sample (ground platforms; the 2D experiments).
    tag_index, lever_arms
        With several tags: (K,) tag index of each range and (n_tags, 3) tag
        positions in the body frame (metres). Otherwise ``params.lever_arm``.
    """
    imu_t = np.asarray(imu_t, dtype=float)
    if imu_t.ndim != 1 or imu_t.size < 2 or np.any(np.diff(imu_t) <= 0):
        raise InputError("IMU times must be strictly increasing (at least two samples)")
    order = np.argsort(range_t, kind="stable")
    rt = np.asarray(range_t, dtype=float)[order]
    ai = np.asarray(anchor_index)[order]
    rv = np.asarray(ranges, dtype=float)[order]
    keep = np.isfinite(rv) & (rt >= imu_t[0])
    rt, ai, rv = rt[keep], ai[keep], rv[keep]
    levers: list[np.ndarray | None] = [None] * rt.size
    if lever_arms is not None:
        ti = np.zeros(len(order), dtype=int) if tag_index is None else np.asarray(tag_index)
        L = np.asarray(lever_arms, dtype=float)
        levers = list(L[ti[order][keep]])
    rs = np.asarray(sigma(rv), dtype=float) if callable(sigma) else np.full(rv.shape, sigma)
    A = np.asarray(anchors, dtype=float)
    M = imu_t.size
    out_p = np.empty((M, 3))
    out_v = np.empty((M, 3))
    out_q = np.empty((M, 4))
    out_ab = np.empty((M, 3))
    out_wb = np.empty((M, 3))
    out_P = np.empty((M, 15))
    j = 0
    K = rt.size
    t_now = imu_t[0]
    accel = np.asarray(accel, dtype=float)
    gyro = np.asarray(gyro, dtype=float)
    n_repairs = 0
    for i in range(M):
        t_next = imu_t[i]
        a_i = accel[i - 1] if i > 0 else accel[0]
        w_i = gyro[i - 1] if i > 0 else gyro[0]
        # covariance once per IMU interval; the nominal state to every range's timestamp
        filt.propagate_covariance(a_i, w_i, t_next - t_now)
        while j < K and rt[j] <= t_next:
            filt.propagate_nominal(a_i, w_i, rt[j] - t_now)
            t_now = rt[j]
            filt.update_range(A[ai[j]], rv[j], rs[j], levers[j])
            j += 1
        filt.propagate_nominal(a_i, w_i, t_next - t_now)
        t_now = t_next
        if height is not None:
            filt.update_height(*height)
        if i % 100 == 0:
            n_repairs += filt.ensure_positive_definite()
        out_p[i] = filt.p
        out_v[i] = filt.v
        out_q[i] = filt.q
        out_ab[i] = filt.ab
        out_wb[i] = filt.wb
        out_P[i] = filt.P.ravel()[::16]
    return EskfTrack(
        t=imu_t,
        p=out_p,
        v=out_v,
        q=out_q,
        accel_bias=out_ab,
        gyro_bias=out_wb,
        P_diag=out_P,
        P_final=filt.P.copy(),
        n_updates=filt.n_updates,
        n_rejected=filt.n_rejected,
        n_covariance_repairs=n_repairs,
    )


def pose_covariance_world(q: np.ndarray, P: np.ndarray) -> np.ndarray:
    """6x6 covariance of ``[dp, r]`` with ``r`` the attitude error in the world frame.

    The filter's attitude error is local (``R_t = R Exp(dtheta)``); the fabflow
    convention (:mod:`fabflow.positioning.result`) is global (``R_t = Exp(r) R``),
    so ``r = R dtheta``.
    """
    R = matrix_from_quat(q)
    J = np.zeros((6, 15))
    J[0:3, 0:3] = np.eye(3)
    J[3:6, 6:9] = R
    C = J @ P @ J.T
    return 0.5 * (C + C.T)


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
