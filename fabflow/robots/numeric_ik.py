"""Numerical inverse kinematics for any chain: damped least squares, batched.

Levenberg-Marquardt on the flange pose error ``e = [p_goal - p; log(R_goal R^T)]``
(base frame): ``dq = (J^T J + lambda^2 I)^-1 J^T e``, with a per-problem damping
that shrinks after a successful step and grows after a failed one, steps
clipped to 0.3 rad and joints clamped to their limits. Many problems (targets x
seeds) are solved at once; no Python loop runs over them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from fabflow.robots.planar_ik import is_pitch_chain, pitch_chain_ik
from fabflow.transforms.so3 import log_so3

if TYPE_CHECKING:
    from fabflow.robots.chain import RobotModel

FloatArray = NDArray[np.float64]

POSITION_TOL = 1e-10
"""Convergence threshold on the position error (metres)."""

ROTATION_TOL = 1e-10
"""Convergence threshold on the orientation error (radians)."""


def pose_error(T: FloatArray, T_goal: FloatArray, axis_only: bool = False) -> FloatArray:
    """Pose error ``[dp; dr]`` (metres, radians) in the base frame, shape ``(N, 6)``.

    With ``axis_only`` the rotation error only tilts the flange z axis onto the
    goal's z axis (rotation about the axis is free).
    """
    ep = T_goal[:, :3, 3] - T[:, :3, 3]
    if axis_only:
        z, zg = T[:, :3, 2], T_goal[:, :3, 2]
        cr = np.cross(z, zg)
        s = np.linalg.norm(cr, axis=1, keepdims=True)
        c = np.sum(z * zg, axis=1, keepdims=True)
        ang = np.arctan2(s, c)
        er = np.where(s > 1e-15, cr / np.maximum(s, 1e-300) * ang, 0.0)
    else:
        er = log_so3(T_goal[:, :3, :3] @ np.swapaxes(T[:, :3, :3], 1, 2))
    return np.concatenate([ep, er], axis=1)


def dls_solve(
    robot: RobotModel,
    T_goal: FloatArray,
    q0: FloatArray,
    *,
    axis_only: bool = False,
    max_iter: int = 200,
    position_tol: float = POSITION_TOL,
    rotation_tol: float = ROTATION_TOL,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Solve many IK problems by damped least squares.

    Parameters
    ----------
    robot
        The chain.
    T_goal
        ``(N, 4, 4)`` goal flange poses in the base frame (metres).
    q0
        ``(N, dof)`` start configurations (radians).
    axis_only
        Only position and the direction of the flange z axis are goals.
    max_iter
        Iteration limit.
    position_tol, rotation_tol
        Convergence thresholds (metres, radians).

    Returns
    -------
    q : numpy.ndarray
        ``(N, dof)`` final configurations (radians, within limits).
    converged : numpy.ndarray
        ``(N,)`` bool: both errors below their thresholds.
    """
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    q = np.clip(np.array(q0, dtype=float), lo, hi)
    n = q.shape[0]
    lam = np.full(n, 1e-2)
    err = pose_error(robot.fk(q), T_goal, axis_only)
    cost = np.sum(err**2, axis=1)
    eye = np.eye(robot.dof)
    active = np.arange(n)

    def done(e: FloatArray) -> NDArray[np.bool_]:
        return (np.linalg.norm(e[:, :3], axis=1) < position_tol) & (
            np.linalg.norm(e[:, 3:], axis=1) < rotation_tol
        )

    converged = done(err)
    active = active[~converged]
    for _ in range(max_iter):
        if active.size == 0:
            break
        qa, ea = q[active], err[active]
        J = robot.jacobian(qa)
        if axis_only:
            z = robot.fk(qa)[:, :3, 2]
            P = np.eye(3) - z[:, :, None] * z[:, None, :]
            J = np.concatenate([J[:, :3], P @ J[:, 3:]], axis=1)
        JtJ = np.swapaxes(J, 1, 2) @ J
        Jte = (np.swapaxes(J, 1, 2) @ ea[:, :, None])[..., 0]
        la = lam[active]
        dq = np.linalg.solve(JtJ + (la**2)[:, None, None] * eye, Jte[..., None])[..., 0]
        scale = np.maximum(1.0, np.max(np.abs(dq), axis=1) / 0.3)
        q_new = np.clip(qa + dq / scale[:, None], lo, hi)
        e_new = pose_error(robot.fk(q_new), T_goal[active], axis_only)
        c_new = np.sum(e_new**2, axis=1)
        better = c_new < cost[active]
        idx = active[better]
        q[idx], err[idx], cost[idx] = q_new[better], e_new[better], c_new[better]
        lam[idx] = np.maximum(lam[idx] * 0.3, 1e-6)
        worse = active[~better]
        lam[worse] = np.minimum(lam[worse] * 4.0, 1e3)
        fin = done(err[active])
        converged[active[fin]] = True
        stuck = lam[active] >= 1e3
        active = active[~fin & ~stuck]
    return q, converged


N_SEEDS = 16
"""Number of random start configurations :func:`solve_seeds` tries besides the reference."""


def solve_seeds(robot: RobotModel, T_goal: FloatArray, q_ref: FloatArray | None) -> FloatArray:
    """IK solutions of one pose for a chain without a complete closed form.

    Pitch chains (the BROKK) take the sampled closed-form family of
    :func:`fabflow.robots.planar_ik.pitch_chain_ik` that matches the full pose,
    plus a damped-least-squares solution from ``q_ref`` (the nearest member of the
    family in the continuous sense). Other chains run damped least squares from
    the reference and a fixed set of seeds.

    Parameters
    ----------
    robot
        The chain.
    T_goal
        4x4 goal flange pose in the base frame.
    q_ref
        Reference configuration (radians); None uses mid-range.

    Returns
    -------
    numpy.ndarray
        ``(K, dof)`` distinct solutions within the limits (radians), flange pose
        within 1e-9 m / 1e-9 rad of the goal.
    """
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    ref = 0.5 * (lo + hi) if q_ref is None else np.asarray(q_ref, dtype=float)
    T = np.asarray(T_goal, dtype=float)
    if is_pitch_chain(robot):
        fam, valid = pitch_chain_ik(robot, T[None])
        cand = fam[0][valid[0]]
        q, ok = dls_solve(robot, T[None], ref[None])
        cand = np.vstack([q[ok], cand])
    else:
        rng = np.random.default_rng(0)
        seeds = np.vstack([ref[None], rng.uniform(lo, hi, size=(N_SEEDS, robot.dof))])
        q, ok = dls_solve(robot, np.broadcast_to(T, (seeds.shape[0], 4, 4)), seeds)
        cand = q[ok]
    if cand.shape[0] == 0:
        return cand
    e = pose_error(robot.fk(cand), np.broadcast_to(T, (cand.shape[0], 4, 4)))
    good = (
        (np.linalg.norm(e[:, :3], axis=1) < 1e-9)
        & (np.linalg.norm(e[:, 3:], axis=1) < 1e-9)
        & robot.within_limits(cand)
    )
    sols = cand[good]
    keep: list[int] = []
    for i in range(sols.shape[0]):
        if not any(np.max(np.abs(sols[i] - sols[j])) < 1e-6 for j in keep):
            keep.append(i)
    return sols[keep]
