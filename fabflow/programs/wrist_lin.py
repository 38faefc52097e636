"""Linear moves past the wrist singularity with the wrist axes interpolated.

Near the wrist singularity (A5 at 0, axes 4 and 6 in line) a straight tool
path with a fixed orientation sends A4 and A6 spinning, and a path that crosses
it takes A5 through 0. That is a change of the arm's configuration (KUKA
Status bit 2, ABB cfx bit 0) inside the line, which a controller refuses. The
vendors' answer is to keep the tool centre point on the line and let the
orientation follow the wrist axes, interpolated from the start configuration
to an end configuration of the same status: KUKA ``$ORI_TYPE = #JOINT``, ABB
``SingArea \\Wrist``. Near the singularity A4 and A6 turn about nearly the same
axis, so the orientation deviates little on the way, and the end is exact.

:func:`wrist_interpolated_path` computes those joint values: A4-A6 linear in
the path fraction, A1-A3 solved (Newton, all samples at once) so that the tool
centre point is on the line. It also returns the largest orientation
deviation from the straight move, which the caller bounds.
"""

from __future__ import annotations

import numpy as np

from fabflow.programs.motion_checks import configuration_of
from fabflow.robots.chain import RobotModel
from fabflow.transforms.so3 import exp_so3, log_so3, skew

MAX_DEVIATION_DEG = 2.0
"""Largest tool orientation deviation (degrees) accepted on a wrist-interpolated
linear move; beyond it the move is left as it is (and reported)."""
_NEWTON_STEPS = 30
_POSITION_TOL = 1e-6
"""Tool centre point accuracy of the solved samples (metres)."""


def same_status_ends(
    robot: RobotModel, q_start: np.ndarray, q_branches: np.ndarray, valid: np.ndarray
) -> np.ndarray:
    """End configurations with A5 on the side of ``q_start``, every turn of A4 and A6.

    Near the singularity A4 and A6 must turn half a turn in opposite senses for
    the orientation to stay: which turns do that depends on the axes' sign
    conventions, so every turn within the limits is a candidate (the caller keeps
    the one whose orientation deviates least).

    Parameters
    ----------
    robot
        The robot.
    q_start
        ``(dof,)`` configuration at the start of the move (radians).
    q_branches, valid
        ``(K, dof)`` inverse-kinematics branches of the end target and their validity.

    Returns
    -------
    numpy.ndarray
        ``(m, dof)`` candidates within the joint limits (``m`` may be 0).
    """
    side = np.sign(q_start[4]) or 1.0
    ends = robot.nearest_turn(q_branches[valid & (np.sign(q_branches[:, 4]) == side)], q_start)
    # the start's whole configuration (shoulder and elbow too), not only A5's side
    ends = ends[configuration_of(robot, ends) == configuration_of(robot, q_start[None])[0]]
    turns = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], dtype=float)
    out = np.repeat(ends, len(turns), axis=0)
    out[:, [3, 5]] += 2.0 * np.pi * np.tile(turns, (len(ends), 1))
    return out[robot.within_limits(out)]


def wrist_interpolated_path(
    robot: RobotModel,
    q_start: np.ndarray,
    q_end: np.ndarray,
    T_base_tool: np.ndarray,
    T_flange_tool: np.ndarray,
) -> tuple[np.ndarray, float] | None:
    """Joint values along a linear move with the wrist axes interpolated.

    Parameters
    ----------
    robot
        A six-axis robot.
    q_start, q_end
        ``(6,)`` configurations at the start and at the target, of the same
        status (radians).
    T_base_tool
        ``(k, 4, 4)`` the straight move's samples (base frame, metres), the
        target last, uniformly spaced along the line.
    T_flange_tool
        The tool centre point in the flange frame.

    Returns
    -------
    tuple or None
        ``(path, deviation)``: ``(k, 6)`` joint values (the last is ``q_end``)
        and the largest orientation deviation from the straight move
        (radians); None when A1-A3 cannot keep the tool centre point on the
        line within the joint limits.
    """
    k = len(T_base_tool)
    s = (np.arange(k) + 1.0) / k
    q = q_start + s[:, None] * (q_end - q_start)
    t_tool = T_flange_tool[:3, 3]
    target = T_base_tool[:, :3, 3]
    for step in range(_NEWTON_STEPS + 1):
        T = robot.fk(q)
        lever = T[:, :3, :3] @ t_tool
        residual = T[:, :3, 3] + lever - target
        if np.abs(residual).max() < _POSITION_TOL:
            break
        if step == _NEWTON_STEPS:
            return None
        J = robot.jacobian(q)
        J_arm = J[:, :3, :3] - skew(lever) @ J[:, 3:, :3]
        try:
            q[:, :3] -= np.linalg.solve(J_arm, residual[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            return None
    if not robot.within_limits(q).all() or np.abs(q[-1] - q_end).max() > 1e-6:
        return None
    R = (robot.fk(q) @ T_flange_tool)[:, :3, :3]
    deviation = np.linalg.norm(log_so3(T_base_tool[:, :3, :3].transpose(0, 2, 1) @ R), axis=1)
    return q, float(deviation.max())


MAX_JOINT_BOW = 0.005
"""Largest distance (metres) of the tool centre point from the straight line on a
short linear move made a joint move through A5 = 0 (:func:`joint_move_bow`)."""
_BOW_SAMPLES = 33


def joint_move_bow(
    robot: RobotModel, q_from: np.ndarray, q_to: np.ndarray, T_flange_tool: np.ndarray
) -> tuple[float, float]:
    """How far a joint move strays from the straight move between the same ends.

    Where neither the straight move nor the wrist-interpolated one can pass
    the wrist singularity (A5 at 0), a short move can be made a joint move: a
    controller takes A5 through 0 in a joint move, and on a short descent with
    A1, A4 and A6 standing still the tool's bow off the line is a few
    millimetres while its orientation stays (A2, A3 and A5 turn about parallel
    axes).

    Parameters
    ----------
    robot
        A six-axis robot.
    q_from, q_to
        ``(6,)`` the move's ends (radians).
    T_flange_tool
        The tool centre point in the flange frame.

    Returns
    -------
    bow, deviation
        The largest distance of the tool centre point from the line between the
        ends (metres) and the largest tool rotation off the geodesic between
        the ends' orientations (radians), over the joint-interpolated path.
    """
    s = np.linspace(0.0, 1.0, _BOW_SAMPLES)[:, None]
    T = robot.fk(q_from + s * (q_to - q_from)) @ T_flange_tool
    p = T[:, :3, 3] - T[0, :3, 3]
    chord = p[-1]
    length = float(np.linalg.norm(chord))
    along = p @ chord / length**2 if length > 0.0 else np.zeros(len(p))
    bow = float(np.linalg.norm(p - along[:, None] * chord, axis=1).max())
    R0 = T[0, :3, :3]
    w = log_so3(R0.T @ T[-1, :3, :3])
    R_line = R0 @ exp_so3(s * w)
    deviation = np.linalg.norm(log_so3(R_line.transpose(0, 2, 1) @ T[:, :3, :3]), axis=1)
    return bow, float(deviation.max())
