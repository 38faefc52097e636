"""UWB/IMU fusion: an error-state Kalman filter.

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
  ``G = blockdiag(I, I, I - [dtheta/2]x, I, I)``;
* every range's normalized innovation squared and gate decision are recorded and
  tested (:mod:`~fabflow.positioning.eskf_integrity`; input bounds: ``eskf_input``).

The world z axis is up; gravity is ``(0, 0, -g)``. The baseline without an
IMU is :mod:`fabflow.positioning.cv_ekf`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fabflow.errors import InputError
from fabflow.positioning.eskf_input import check_input
from fabflow.positioning.eskf_integrity import (
    BiasMonitor,
    EskfConsistency,
    bias_onsets,
    consistency,
    rest_gyro_test,
)
from fabflow.transforms.so3 import matrix_from_quat, quat_from_matrix

GRAVITY = 9.81
"""Magnitude of gravity (m/s^2): the filter's model, and the IMU simulator's."""
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


Vec = tuple[float, ...]


def _quat_to_R(q: Vec) -> list[list[float]]:
    # Hot-loop version of transforms.so3.matrix_from_quat for one unit quaternion
    # (the library function validates and broadcasts, ~100x slower per call).
    w, x, y, z = q
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]


def _quat_rotate_right(q: Vec, th: Vec) -> Vec:
    # q (x) q{th}, renormalized; hot-loop version of the library's rotvec/quaternion maths.
    tx, ty, tz = th
    a = math.sqrt(tx * tx + ty * ty + tz * tz)
    if a < 1e-12:
        c, s = 1.0, 0.5
    else:
        c, s = math.cos(0.5 * a), math.sin(0.5 * a) / a
    bw, bx, by, bz = c, s * tx, s * ty, s * tz
    w, x, y, z = q
    ow = w * bw - x * bx - y * by - z * bz
    ox = w * bx + x * bw + y * bz - z * by
    oy = w * by - x * bz + y * bw + z * bx
    oz = w * bz + x * by - y * bx + z * bw
    n = math.sqrt(ow * ow + ox * ox + oy * oy + oz * oz)
    return (ow / n, ox / n, oy / n, oz / n)


def _exp_transpose(th: Vec) -> list[list[float]]:
    # Exp(th)^T for one small rotation vector, via the hot-loop quaternion helpers.
    R = _quat_to_R(_quat_rotate_right((1.0, 0.0, 0.0, 0.0), th))
    return [[R[0][0], R[1][0], R[2][0]], [R[0][1], R[1][1], R[2][1]], [R[0][2], R[1][2], R[2][2]]]


class Eskf:
    """Error-state Kalman filter for UWB ranges and an IMU (see the module docstring).

    The nominal state is kept in plain Python floats and the 15x15 covariance in
    numpy: the filter is sequential, and at this size per-call overhead, not
    arithmetic, sets the speed.

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
        P = np.array(P, dtype=float)
        if P.shape != (15, 15):
            raise InputError(f"ESKF covariance must be 15x15, got {P.shape}")
        self.P = 0.5 * (P + P.T)
        self._p = tuple(float(x) for x in np.asarray(p, dtype=float))
        self._v = tuple(float(x) for x in np.asarray(v, dtype=float))
        qa = np.asarray(q, dtype=float)
        self._q = tuple(float(x) for x in qa / np.linalg.norm(qa))
        self._ab = (0.0, 0.0, 0.0) if accel_bias is None else tuple(map(float, accel_bias))
        self._wb = (0.0, 0.0, 0.0) if gyro_bias is None else tuple(map(float, gyro_bias))
        self._R = _quat_to_R(self._q)
        self._g = -self.params.gravity
        self._lever = tuple(float(x) for x in self.params.lever_arm)
        self.n_updates = 0
        self.n_rejected = 0
        # gain, innovation and its variance of the last applied measurement (for BiasMonitor)
        self.last_update: tuple[np.ndarray, float, float] = (np.zeros(15), 0.0, 1.0)
        self._F = np.eye(15)
        self._F_dt = -1.0
        self._eye3 = np.eye(3)
        self._H = np.zeros(15)
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

    @property
    def p(self) -> np.ndarray:
        """Position of the body origin in the world (m)."""
        return np.array(self._p)

    @property
    def v(self) -> np.ndarray:
        """Velocity in the world (m/s)."""
        return np.array(self._v)

    @property
    def q(self) -> np.ndarray:
        """Attitude quaternion (w, x, y, z) of the body in the world."""
        return np.array(self._q)

    @property
    def R(self) -> np.ndarray:
        """Attitude as a rotation matrix (body to world)."""
        return np.array(self._R)

    @property
    def ab(self) -> np.ndarray:
        """Accelerometer bias estimate (m/s^2, body)."""
        return np.array(self._ab)

    @property
    def wb(self) -> np.ndarray:
        """Gyro bias estimate (rad/s, body)."""
        return np.array(self._wb)

    def propagate(self, accel: Vec, gyro: Vec, dt: float) -> None:
        """Integrate one IMU reading (body specific force, angular rate) over ``dt`` seconds."""
        if dt <= 0.0:
            return
        accel, gyro = tuple(map(float, accel)), tuple(map(float, gyro))
        self.propagate_covariance(accel, gyro, dt)
        self.propagate_nominal(accel, gyro, dt)

    def propagate_nominal(self, accel: Vec, gyro: Vec, dt: float) -> None:
        """Integrate the nominal state only (equation 20, first line); readings as float tuples."""
        if dt <= 0.0:
            return
        ab, wb, R = self._ab, self._wb, self._R
        ax, ay, az = accel[0] - ab[0], accel[1] - ab[1], accel[2] - ab[2]
        wx = R[0][0] * ax + R[0][1] * ay + R[0][2] * az
        wy = R[1][0] * ax + R[1][1] * ay + R[1][2] * az
        wz = R[2][0] * ax + R[2][1] * ay + R[2][2] * az + self._g
        (px, py, pz), (vx, vy, vz) = self._p, self._v
        h = 0.5 * dt
        self._p = (px + (vx + h * wx) * dt, py + (vy + h * wy) * dt, pz + (vz + h * wz) * dt)
        self._v = (vx + wx * dt, vy + wy * dt, vz + wz * dt)
        self._q = _quat_rotate_right(
            self._q, ((gyro[0] - wb[0]) * dt, (gyro[1] - wb[1]) * dt, (gyro[2] - wb[2]) * dt)
        )
        self._R = _quat_to_R(self._q)

    def propagate_covariance(self, accel: Vec, gyro: Vec, dt: float) -> None:
        """Propagate the error covariance over ``dt`` from the current nominal state (eq. 21)."""
        if dt <= 0.0:
            return
        F = self._F
        if dt != self._F_dt:
            F[0:3, 3:6] = self._eye3 * dt
            F[6:9, 12:15] = self._eye3 * (-dt)
            self._F_dt = dt
        R = self._R
        ab, wb = self._ab, self._wb
        ax, ay, az = accel[0] - ab[0], accel[1] - ab[1], accel[2] - ab[2]
        # -R [a]x dt, written out
        F[3:6, 6:9] = [
            [
                (r[2] * ay - r[1] * az) * dt,
                (r[0] * az - r[2] * ax) * dt,
                (r[1] * ax - r[0] * ay) * dt,
            ]
            for r in R
        ]
        F[3:6, 9:12] = [[-r[0] * dt, -r[1] * dt, -r[2] * dt] for r in R]
        F[6:9, 6:9] = _exp_transpose(
            ((gyro[0] - wb[0]) * dt, (gyro[1] - wb[1]) * dt, (gyro[2] - wb[2]) * dt)
        )
        P = F @ self.P @ F.T
        P += P.T
        P *= 0.5
        P.ravel()[::16] += self._q_rate * dt
        self.P = P

    def _correct(self, H: np.ndarray, innovation: float, var: float) -> float:
        """Gate and apply one scalar measurement; returns the squared normalized innovation."""
        PHt = self.P @ H
        S = float(H @ PHt) + var
        nis = innovation * innovation / S
        if not nis <= self.params.gate:  # also rejects a NaN innovation
            self.n_rejected += 1
            return nis
        K = PHt / S
        self.last_update = (K, innovation, S)
        # P - K S K^T: equal to the Joseph form for the optimal gain. It is symmetric in
        # exact arithmetic; propagate_covariance symmetrizes once per IMU interval and
        # run_eskf checks positive definiteness.
        P = self.P
        P -= np.outer(K, PHt)
        dx = (K * innovation).tolist()
        p, v, ab, wb = self._p, self._v, self._ab, self._wb
        self._p = (p[0] + dx[0], p[1] + dx[1], p[2] + dx[2])
        self._v = (v[0] + dx[3], v[1] + dx[4], v[2] + dx[5])
        tx, ty, tz = dx[6], dx[7], dx[8]
        self._q = _quat_rotate_right(self._q, (tx, ty, tz))
        self._R = _quat_to_R(self._q)
        self._ab = (ab[0] + dx[9], ab[1] + dx[10], ab[2] + dx[11])
        self._wb = (wb[0] + dx[12], wb[1] + dx[13], wb[2] + dx[14])
        # reset (eq. 28): G = I except its attitude block I - [dtheta/2]x. Its effect on P
        # is of relative order |dtheta|; below 1e-4 rad it is skipped (the paper uses G = I).
        if tx * tx + ty * ty + tz * tz > 1e-8:
            B = np.array(
                [[1.0, 0.5 * tz, -0.5 * ty], [-0.5 * tz, 1.0, 0.5 * tx], [0.5 * ty, -0.5 * tx, 1.0]]
            )
            P[6:9, :] = B @ P[6:9, :]
            P[:, 6:9] = P[:, 6:9] @ B.T
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
        self, anchor: Vec, measured: float, sigma: float, lever: Vec | None = None
    ) -> float:
        """Apply one UWB range (metres) to ``anchor`` with noise ``sigma`` (metres).

        ``lever`` is the tag position in the body frame (``params.lever_arm`` when
        omitted). Returns the squared normalized innovation (the range was
        rejected when it exceeds ``params.gate``).
        """
        lx, ly, lz = self._lever if lever is None else lever
        R = self._R
        px, py, pz = self._p
        dx = px + R[0][0] * lx + R[0][1] * ly + R[0][2] * lz - anchor[0]
        dy = py + R[1][0] * lx + R[1][1] * ly + R[1][2] * lz - anchor[1]
        dz = pz + R[2][0] * lx + R[2][1] * ly + R[2][2] * lz - anchor[2]
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        inv = 1.0 / max(dist, 1e-9)
        ux, uy, uz = dx * inv, dy * inv, dz * inv
        H = self._H
        if lx == 0.0 and ly == 0.0 and lz == 0.0:
            H[:] = (ux, uy, uz, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
        else:
            # d range / d dtheta = (l x (R^T u))^T for the local attitude error
            w0 = R[0][0] * ux + R[1][0] * uy + R[2][0] * uz
            w1 = R[0][1] * ux + R[1][1] * uy + R[2][1] * uz
            w2 = R[0][2] * ux + R[1][2] * uy + R[2][2] * uz
            H[:] = (
                ux, uy, uz, 0, 0, 0,
                ly * w2 - lz * w1, lz * w0 - lx * w2, lx * w1 - ly * w0,
                0, 0, 0, 0, 0, 0,
            )  # fmt: skip
        return self._correct(H, measured - dist, sigma * sigma)

    def update_height(self, z: float, sigma: float) -> float:
        """Apply a known height of the body origin (metres), e.g. a platform on a floor."""
        H = self._H
        H[:] = 0.0
        H[2] = 1.0
        return self._correct(H, z - self._p[2], sigma * sigma)


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
        Updates applied (ranges and heights) and ranges rejected by the gate.
    range_t, range_anchor, range_nis, range_gated
        (K,) time (s), anchor index, normalized innovation squared ``nu^2 / S``
        and gate decision of every range applied, in time order.
    consistency
        The run's statistics and tests (:func:`~fabflow.positioning.eskf_integrity.consistency`).
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
    range_t: np.ndarray
    range_anchor: np.ndarray
    range_nis: np.ndarray
    range_gated: np.ndarray
    consistency: EskfConsistency
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
    (after the ranges up to that time), with every range's NIS and gate decision.

    Parameters
    ----------
    filt
        An initialized filter (state at ``imu_t[0]``).
    imu_t, accel, gyro
        (M,) sample times (s) and (M, 3) readings; times strictly increasing,
        within the bounds of :mod:`~fabflow.positioning.eskf_input`.
    range_t, anchor_index, ranges
        (K,) range timestamps (s), anchor indices and calibrated ranges (m); NaN
        ranges are skipped. Sorted by time here. They must lie within the IMU
        record (``RANGE_MARGIN_S``); those in the margin are not applied.
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

    Raises
    ------
    InputError
        IMU times not increasing, samples beyond the bounds, ranges outside the IMU record.
    """
    imu_t = np.asarray(imu_t, dtype=float)
    accel, gyro = np.asarray(accel, dtype=float), np.asarray(gyro, dtype=float)
    order = np.argsort(range_t, kind="stable")
    rt = np.asarray(range_t, dtype=float)[order]
    ai = np.asarray(anchor_index)[order]
    rv = np.asarray(ranges, dtype=float)[order]
    check_input(imu_t, accel, gyro, rt[np.isfinite(rv)])
    keep = np.isfinite(rv) & (rt >= imu_t[0]) & (rt <= imu_t[-1])
    rt, ai, rv = rt[keep], ai[keep], rv[keep]
    levers: list[np.ndarray | None] = [None] * rt.size
    if lever_arms is not None:
        ti = np.zeros(len(order), dtype=int) if tag_index is None else np.asarray(tag_index)
        L = np.asarray(lever_arms, dtype=float)
        levers = [tuple(x) for x in L[ti[order][keep]].tolist()]
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
    t_now = float(imu_t[0])
    acc_l = [tuple(a) for a in accel.tolist()]
    gyr_l = [tuple(g) for g in gyro.tolist()]
    anc_l = [tuple(a) for a in A.tolist()]
    rt_l, ai_l, rv_l, rs_l = rt.tolist(), ai.tolist(), rv.tolist(), rs.tolist()
    nis_l = [math.nan] * K
    gate = filt.params.gate
    monitor = BiasMonitor(A.shape[0], bias_onsets(rt, float(imu_t[-1])))
    n_repairs = 0
    for i in range(M):
        t_next = float(imu_t[i])
        a_i = acc_l[i - 1] if i > 0 else acc_l[0]
        w_i = gyr_l[i - 1] if i > 0 else gyr_l[0]
        # covariance once per IMU interval; the nominal state to every range's timestamp
        if i > 0:
            filt.propagate_covariance(a_i, w_i, t_next - t_now)
            monitor.propagate(filt._F)
        while j < K and rt_l[j] <= t_next:
            filt.propagate_nominal(a_i, w_i, rt_l[j] - t_now)
            t_now = rt_l[j]
            nis_l[j] = filt.update_range(anc_l[ai_l[j]], rv_l[j], rs_l[j], levers[j])
            if nis_l[j] <= gate:
                monitor.correct(filt._H, *filt.last_update, ai_l[j], t_now)
            j += 1
        filt.propagate_nominal(a_i, w_i, t_next - t_now)
        t_now = t_next
        if height is not None and filt.update_height(*height) <= gate:
            monitor.correct(filt._H, *filt.last_update)
        if i % 100 == 0:
            n_repairs += filt.ensure_positive_definite()
        out_p[i] = filt._p
        out_v[i] = filt._v
        out_q[i] = filt._q
        out_ab[i] = filt._ab
        out_wb[i] = filt._wb
        out_P[i] = filt.P.ravel()[::16]
    nis = np.array(nis_l)
    gated = ~(nis <= gate)
    rest = rest_gyro_test(imu_t, gyro, out_p, filt.wb, filt.P[12:15, 12:15], filt.params.gyro_noise)
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
        range_t=rt,
        range_anchor=ai,
        range_nis=nis,
        range_gated=gated,
        consistency=consistency(float(imu_t[-1]), rt, nis, gated, monitor.tests(), rest),
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
