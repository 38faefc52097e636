"""Closed-form IK family of a slewing pitch chain (excavator / demolition-machine arms).

Joint 1 slews about the vertical; joints 2..n pitch about parallel horizontal
axes (DH ``alpha = 0``, ``d = 0`` after the first link), and the tool points
along the last link. The arm is redundant for a tool pose (n - 1 pitch joints
for the three planar coordinates r, z and tool pitch), so the solutions form a
one-parameter family: for each sampled absolute angle of the second-to-last
link the remaining two-link problem is solved in closed form (elbow up/down).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from fabflow.robots.chain import RobotModel

FloatArray = NDArray[np.float64]


def is_pitch_chain(robot: RobotModel) -> bool:
    """Whether the model has the slew + parallel pitch joints structure (5 joints)."""
    return (
        robot.dh is not None
        and robot.dof == 5
        and bool(np.all(robot.dh[1:, 1] == 0.0))
        and bool(np.all(robot.dh[1:, 2] == 0.0))
        and bool(np.all(robot.dh[:, 3] == 0.0))
        and bool(np.all(robot.joint_sign == 1.0))
        and abs(robot.dh[0, 1] - np.pi / 2) < 1e-12
        and np.allclose(robot.T_n_flange[:3, 2], [1.0, 0.0, 0.0])
        and np.allclose(robot.T_n_flange[:3, 3], 0.0)
    )


def pitch_chain_ik(
    robot: RobotModel, T_base_flange: FloatArray, n_phi: int = 48
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Sampled closed-form solutions for a tool position and tool axis direction.

    Only the flange position and its z axis (the tool axis) are used; the roll
    about the tool axis follows from the slew angle.

    Parameters
    ----------
    robot
        A model for which :func:`is_pitch_chain` holds.
    T_base_flange
        ``(N, 4, 4)`` goal flange poses (metres).
    n_phi
        Samples of the absolute angle of link 4 over a full turn.

    Returns
    -------
    q : numpy.ndarray
        ``(N, 4 * n_phi, 5)`` joint values (radians): slew front/back x elbow
        up/down x sampled link-4 angle.
    valid : numpy.ndarray
        ``(N, 4 * n_phi)`` bool: the solution exists, the tool axis lies in the
        arm plane (within 1e-9) and all joints are within limits.
    """
    T = np.asarray(T_base_flange, dtype=float)
    a = robot.dh[:, 0]
    d1 = robot.dh[0, 2]
    p = T[:, :3, 3]
    u = T[:, :3, 2]
    beta = np.arctan2(p[:, 1], p[:, 0])
    phi4 = np.arange(n_phi) * (2 * np.pi / n_phi) - np.pi
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    out_q = []
    out_ok = []
    for q1 in (beta, beta + np.pi):
        c1, s1 = np.cos(q1), np.sin(q1)
        # Planar coordinates: rho along the arm's horizontal direction, h up.
        rho = p[:, 0] * c1 + p[:, 1] * s1 - a[0]
        h = p[:, 2] - d1
        u_rho = u[:, 0] * c1 + u[:, 1] * s1
        u_perp = -u[:, 0] * s1 + u[:, 1] * c1
        off_plane = np.abs(u_perp) > 1e-9
        theta = np.arctan2(u[:, 2], u_rho)
        wx = rho - a[4] * np.cos(theta)
        wz = h - a[4] * np.sin(theta)
        ex = wx[:, None] - a[3] * np.cos(phi4)[None, :]
        ez = wz[:, None] - a[3] * np.sin(phi4)[None, :]
        D2 = ex**2 + ez**2
        c3 = (D2 - a[1] ** 2 - a[2] ** 2) / (2 * a[1] * a[2])
        exists = np.abs(c3) <= 1.0
        acos3 = np.arccos(np.clip(c3, -1.0, 1.0))
        for sgn in (1.0, -1.0):
            q3 = sgn * acos3
            q2 = np.arctan2(ez, ex) - np.arctan2(a[2] * np.sin(q3), a[1] + a[2] * np.cos(q3))
            q4 = phi4[None, :] - q2 - q3
            q5 = theta[:, None] - phi4[None, :]
            q = np.stack([np.broadcast_to(q1[:, None], q2.shape), q2, q3, q4, q5], axis=-1)
            q = np.pi - np.mod(np.pi - q, 2 * np.pi)
            ok = exists & ~off_plane[:, None] & np.all((q >= lo) & (q <= hi), axis=-1)
            out_q.append(q)
            out_ok.append(ok)
    return np.concatenate(out_q, axis=1), np.concatenate(out_ok, axis=1)
