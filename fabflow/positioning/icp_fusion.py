"""EKF fusion of 10 Hz ICP poses with 100 Hz kinematics (paper 000, section III-D).

The state is the end-effector pose ``T_world_ee`` and its twist ``u = [v, w]``
(linear and angular velocity in the world frame). The filter is an error-state
EKF in fabflow's pose convention (errors ``[d, r]`` in the world frame,
``T_true = [Exp(r) R, t + d]``) plus the twist error:

* prediction (constant velocity): ``T <- [Exp(w dt) R, t + v dt]``, error
  transition ``[[I, I dt], [0, I]]``, white acceleration noise;
* kinematics update (every kinematics sample, 100 Hz): the increment between two
  consecutive kinematic poses, divided by ``dt``, measures the twist. Kinematics
  are locally accurate but globally biased (base localization, arm deflection),
  so only their increments are used;
* ICP update (10 Hz): the scan-to-map pose measures the pose directly, with the
  ICP covariance.

The output is a pose at every kinematics sample (100 Hz) that stays consistent
with the map like ICP, but moves smoothly between scans like the kinematics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.transforms.se3 import perturb, pose_error
from fabflow.transforms.so3 import exp_so3, log_so3

FloatArray = NDArray[np.float64]


@dataclass
class FusionParams:
    """Noise model of the ICP/kinematics EKF.

    Attributes
    ----------
    accel_sigma, angular_accel_sigma
        White linear (m/s^2) and angular (rad/s^2) acceleration of the process model.
    kin_velocity_sigma, kin_rate_sigma
        Noise of the twist measured from kinematic increments (m/s, rad/s).
    icp_covariance
        Default 6x6 ICP pose covariance when none is given per scan (m^2, rad^2).
    """

    accel_sigma: float = 0.5
    angular_accel_sigma: float = 0.5
    kin_velocity_sigma: float = 0.02
    kin_rate_sigma: float = 0.01
    icp_covariance: tuple[float, ...] = (0.005**2,) * 3 + (np.radians(0.3) ** 2,) * 3


@dataclass(frozen=True, eq=False)
class FusionResult:
    """Fused poses at the kinematics rate.

    Attributes
    ----------
    t
        ``(n,)`` times (seconds).
    T_world_ee
        ``(n, 4, 4)`` fused poses.
    covariance
        ``(n, 6, 6)`` pose covariances (fabflow convention).
    twist
        ``(n, 6)`` estimated ``[v, w]`` (world frame).
    """

    t: FloatArray
    T_world_ee: FloatArray
    covariance: FloatArray
    twist: FloatArray


def fuse_icp_kinematics(
    t_kin: ArrayLike,
    T_kin: ArrayLike,
    t_icp: ArrayLike,
    T_icp: ArrayLike,
    icp_covariances: ArrayLike | None = None,
    params: FusionParams | None = None,
) -> FusionResult:
    """Run the EKF over a kinematics stream and an ICP stream.

    Parameters
    ----------
    t_kin, T_kin
        ``(n,)`` increasing times and ``(n, 4, 4)`` kinematic end-effector poses.
    t_icp, T_icp
        ``(m,)`` times and ``(m, 4, 4)`` ICP poses (applied at the first kinematics
        sample at or after their time).
    icp_covariances
        ``(m, 6, 6)`` ICP covariances; ``params.icp_covariance`` when ``None``.
    params
        Noise model (defaults of :class:`FusionParams` when ``None``).

    Returns
    -------
    FusionResult
        One fused pose per kinematics sample.
    """
    params = params or FusionParams()
    tk = np.asarray(t_kin, dtype=float)
    Tk = np.asarray(T_kin, dtype=float)
    ti = np.asarray(t_icp, dtype=float)
    Ti = np.asarray(T_icp, dtype=float)
    if Tk.shape != (len(tk), 4, 4) or Ti.shape != (len(ti), 4, 4) or len(tk) < 2:
        raise InputError("expected (n,) times with (n, 4, 4) poses for both streams, n >= 2")
    if np.any(np.diff(tk) <= 0) or np.any(np.diff(ti) < 0):
        raise InputError("times must increase")
    Ci = (
        np.broadcast_to(np.diag(params.icp_covariance), (len(ti), 6, 6))
        if icp_covariances is None
        else np.asarray(icp_covariances, dtype=float)
    )
    R_kin = np.diag([params.kin_velocity_sigma**2] * 3 + [params.kin_rate_sigma**2] * 3)
    first_icp = ti[0] if len(ti) else np.inf
    T = (Ti[0] if len(ti) and first_icp <= tk[0] else Tk[0]).copy()
    u = np.zeros(6)
    P = np.diag([0.05**2] * 3 + [np.radians(2.0) ** 2] * 3 + [0.1**2] * 3 + [0.1**2] * 3)
    H_u = np.hstack([np.zeros((6, 6)), np.eye(6)])
    H_T = np.hstack([np.eye(6), np.zeros((6, 6))])
    n = len(tk)
    # kinematic increments -> twist measurements (world frame), all at once
    dts = np.diff(tk)[:, None]
    dR = Tk[1:, :3, :3] @ Tk[:-1, :3, :3].transpose(0, 2, 1)
    z_kin = np.hstack([(Tk[1:, :3, 3] - Tk[:-1, :3, 3]) / dts, log_so3(dR) / dts])
    out_T = np.empty((n, 4, 4))
    out_C = np.empty((n, 6, 6))
    out_u = np.empty((n, 6))
    j = 0
    for k in range(n):  # a recursive filter: one step per kinematics sample
        if k > 0:
            dt = tk[k] - tk[k - 1]
            T = T.copy()
            T[:3, :3] = exp_so3(u[3:] * dt) @ T[:3, :3]
            T[:3, 3] = T[:3, 3] + u[:3] * dt
            F = np.eye(12)
            F[:6, 6:] = np.eye(6) * dt
            qa, qw = params.accel_sigma**2, params.angular_accel_sigma**2
            q = np.array([qa] * 3 + [qw] * 3)
            Q = np.zeros((12, 12))
            Q[:6, :6] = np.diag(q * dt**4 / 4)
            Q[:6, 6:] = Q[6:, :6] = np.diag(q * dt**3 / 2)
            Q[6:, 6:] = np.diag(q * dt**2)
            P = F @ P @ F.T + Q
            T, u, P = _update(T, u, P, z_kin[k - 1] - u, H_u, R_kin)
        while j < len(ti) and ti[j] <= tk[k]:
            T, u, P = _update(T, u, P, pose_error(T, Ti[j]), H_T, Ci[j])
            j += 1
        out_T[k] = T
        out_C[k] = P[:6, :6]
        out_u[k] = u
    return FusionResult(t=tk, T_world_ee=out_T, covariance=out_C, twist=out_u)


def _update(
    T: FloatArray,
    u: FloatArray,
    P: FloatArray,
    innovation: FloatArray,
    H: FloatArray,
    R: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    dx = K @ innovation
    I_KH = np.eye(len(P)) - K @ H
    P = I_KH @ P @ I_KH.T + K @ R @ K.T
    return perturb(T, dx[:6]), u + dx[6:], P
