"""The print head's tracking controller: feed-forward along the path plus feedback on its pose.

Two loops, as on a hydraulic machine:

* **joints** (100 Hz, on the joint sensors): each valve opens by the joint's
  feed-forward speed plus a proportional correction towards its command,
  ``u = (qd_ff(t + T_d + tau) + k_j (q_cmd - q_meas)) / v_max``. The
  feed-forward is taken one dead time and one lag ahead: the path is known in
  advance, so the valves open before the joints must move. ``k_j`` puts the
  joint loop's crossover at ``0.5 / (T_d + tau)``, where the delay costs less
  than 30 degrees of phase (:meth:`HydraulicJoints.for_robot`). The valve's
  deadband is inverted (``sign(u) (db + (1 - db) |u|)``), as a valve
  amplifier's deadband compensation does, so that small flows are not lost;
* **the print head** (closed loop only, on the fused end-effector estimate): a
  PI offset on the task error ``e = x_ref - x_est`` (position, and
  orientation as a rotation vector), mapped to joint offsets by CLIK's
  weighted damped pseudo-inverse (DLS + WLN, paper 004 eq. 7) at the
  feed-forward configuration: ``q_cmd = q_ff + J+ (k_p e + k_i int e)``. Its
  bandwidth ``k_i / (1 + k_p)`` (0.33 rad/s) stays an order of magnitude below
  the joint loop's, where the ICP latency and the joints' lag cost little phase.

Open loop is the same controller without the second loop: the joints follow
the path's inverse kinematics on their own sensors, so every error of the
kinematic chain (base pose, geometry, joint biases) reaches the print.
The feed-forward joint path is the closed-form inverse kinematics of the
reference (nominal model, the base where the GNSS puts it at the start).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fabflow.errors import InputError
from fabflow.robots.chain import RobotModel
from fabflow.robots.clik import Clik
from fabflow.robots.hydraulic import HydraulicJoints
from fabflow.tracking.reference import Reference
from fabflow.transforms.se3 import inv_T, make_T
from fabflow.transforms.so3 import log_so3_one

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TrackingGains:
    """Gains of the print-head loop (SI units; the project's ``tracking`` section sets them).

    The correction is a task-space offset ``c = kp e + ki int e``: with a
    perfect, immediate estimate a constant bias decays as ``exp(-t ki / (1 +
    kp))`` (3 s for the project's defaults, 0.5 and 0.5 1/s), without overshoot.

    Attributes
    ----------
    kp
        Proportional gain on the task error (dimensionless: the share of the error
        corrected at once).
    ki
        Integral gain (1/s): removes the kinematic chain's slowly varying bias.
    max_correction
        Bound of the integral's position part and of the whole position
        correction (metres): a wrong estimate cannot drag the print head further.
    """

    kp: float
    ki: float
    max_correction: float = 0.15


@dataclass(frozen=True, eq=False)
class FeedForward:
    """The reference in joint space.

    Attributes
    ----------
    q, qd
        ``(K, dof)`` joint path (radians) and speeds (rad/s) of the reference.
    pinv
        ``(K, dof, 6)`` CLIK pseudo-inverse of the nozzle's task Jacobian (base frame)
        at each reference configuration.
    """

    q: FloatArray
    qd: FloatArray
    pinv: FloatArray


def feed_forward(
    robot: RobotModel,
    reference: Reference,
    R_ref: FloatArray,
    T_world_base: FloatArray,
    T_flange_tool: FloatArray,
) -> FeedForward:
    """Joint path of the reference by closed-form IK, and the CLIK pseudo-inverse along it.

    Parameters
    ----------
    robot
        The nominal machine model.
    reference
        The nozzle path (world frame).
    R_ref
        The nozzle's orientation in the world (constant along the path).
    T_world_base, T_flange_tool
        Where the machine believes its base is, and its tool.

    Returns
    -------
    FeedForward
        The joint path, its speeds and the pseudo-inverse along it.

    Raises
    ------
    InputError
        When a point of the path is out of the machine's reach or joint limits.
    """
    K = len(reference.t)
    T_world_tool = make_T(np.broadcast_to(R_ref, (K, 3, 3)), reference.p)
    T_base_flange = inv_T(T_world_base) @ T_world_tool @ inv_T(T_flange_tool)
    q_all, valid = robot.ik_batch(T_base_flange, q_ref=robot.q_nominal)
    ok = valid.all(axis=0)
    if not ok.any():
        k = int(np.argmin(valid.sum(axis=1)))
        raise InputError(
            f"the print path leaves the machine's reach at t = {reference.t[k]:.2f} s "
            f"(nozzle at {np.round(reference.p[k], 3).tolist()} m)"
        )
    ref = robot.q_nominal if robot.q_nominal is not None else np.zeros(robot.dof)
    branches = np.flatnonzero(ok)
    branch = branches[np.argmin(np.linalg.norm(q_all[0, branches] - ref, axis=1))]
    q = np.unwrap(q_all[:, branch], axis=0)
    if not robot.within_limits(q).all():  # a joint wound past its limit along the path
        k = int(np.argmin(robot.within_limits(q)))
        raise InputError(
            f"the print path drives a joint past its limit at t = {reference.t[k]:.2f} s "
            f"(nozzle at {np.round(reference.p[k], 3).tolist()} m)"
        )
    qd = np.gradient(q, reference.t, axis=0)
    clik = Clik(robot, "pose")
    J = robot.jacobian(q)
    r = (T_base_flange[:, :3, :3] @ T_flange_tool[:3, 3])[:, None, :]
    J[:, :3] = J[:, :3] - np.cross(r, np.swapaxes(J[:, 3:], 1, 2)).transpose(0, 2, 1)
    g = clik.joint_limit_gradient(q)
    towards = np.vstack([np.zeros((1, robot.dof), bool), g[1:] >= g[:-1]])
    w = np.where(np.isfinite(g), np.where(towards, 1.0 + g, 1.0), 1e12)
    m = np.sqrt(np.maximum(np.linalg.det(J @ np.swapaxes(J, 1, 2)), 0.0))
    lam = np.where(m < clik.m_threshold, clik.gains.k_damping * (1 - m / clik.m_threshold), 0.0)
    return FeedForward(q=q, qd=qd, pinv=clik.pinv(J, w, lam))


class TrackingController:
    """The two loops, stepped at the reference's rate.

    Parameters
    ----------
    ff
        The reference in joint space.
    reference
        The nozzle path (world frame).
    R_ref
        The nozzle's orientation in the world.
    R_world_base
        The base's orientation as the machine believes it (maps world errors to the base).
    joints
        The hydraulic joints (speeds, dead time and lag set the joint loop).
    gains
        The print-head loop's gains; ``None``: open loop (joints only).
    """

    def __init__(
        self,
        ff: FeedForward,
        reference: Reference,
        R_ref: FloatArray,
        R_world_base: FloatArray,
        joints: HydraulicJoints,
        gains: TrackingGains | None,
    ) -> None:
        self.ff = ff
        self.reference = reference
        self.R_ref = R_ref
        self.R_base_world = R_world_base.T
        self.gains = gains
        self.v_max = np.asarray(joints.v_max, dtype=float)
        # a loop without delay or lag still has its sampling: at most a quarter step per period
        self.k_joint = 0.5 / max(joints.dead_time + joints.tau, 2.0 * joints.dt)
        self.advance = round((joints.dead_time + joints.tau) / joints.dt)
        self.dt = joints.dt
        self.deadband = joints.deadband
        self.integral = np.zeros(6)

    def valves(self, k: int, q_meas: FloatArray, T_est: FloatArray | None) -> FloatArray:
        """Valve commands at reference sample ``k``.

        Parameters
        ----------
        k
            Index of the reference sample (the current time); negative while the
            machine holds the start before printing.
        q_meas
            The joints as the machine measures them (radians).
        T_est
            The nozzle's estimated pose in the world (closed loop; ignored in open loop).

        Returns
        -------
        numpy.ndarray
            ``(dof,)`` valve commands (fractions of full opening, unclipped).
        """
        K = len(self.ff.q)
        kk = min(max(k, 0), K - 1)
        q_cmd = self.ff.q[kk]
        if self.gains is not None and T_est is not None:
            e = np.empty(6)
            e[:3] = self.reference.p[kk] - T_est[:3, 3]
            e[3:] = log_so3_one(self.R_ref @ T_est[:3, :3].T)
            g = self.gains
            self.integral += e * self.dt
            n = np.linalg.norm(self.integral[:3]) * g.ki
            if n > g.max_correction:
                self.integral *= g.max_correction / n
            corr = g.kp * e + g.ki * self.integral
            m = np.linalg.norm(corr[:3])
            if m > g.max_correction:
                corr[:3] *= g.max_correction / m
            corr_base = np.concatenate([self.R_base_world @ corr[:3], self.R_base_world @ corr[3:]])
            q_cmd = q_cmd + self.ff.pinv[kk] @ corr_base
        ahead = k + self.advance
        qd_ff = self.ff.qd[ahead] if 0 <= ahead < K else np.zeros_like(q_meas)
        u = (qd_ff + self.k_joint * (q_cmd - q_meas)) / self.v_max
        # the valve's deadband inverted: the opening that makes the flow of u
        db = self.deadband
        return np.sign(u) * (db + (1.0 - db) * np.abs(u)) if db > 0 else u
