"""Following one inverse-kinematics branch along linear moves, without a Python loop.

The fast path of :func:`fabflow.programs.feasibility.solve_moves`: consecutive
samples of a linear move are one controller step apart, so a branch that keeps
its solutions valid, its joint steps small and its speeds within the limits is
the joint path. :func:`follow_branch` follows one move; :func:`follow_branch_chain`
the linear moves after a PTP target at once (a print path's thousands of short
moves), and leaves anything else to the move-by-move search.
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np

from fabflow.programs.motion_checks import A5_ZERO, wrap_angle
from fabflow.robots.chain import RobotModel

MIN_SPEED_FRACTION = 0.1
"""A linear move may be slowed near a singularity so its joints stay within their
speed limits, down to this fraction of its programmed speed; slower is an error."""
MAX_JOINT_STEP = np.pi / 2
"""A joint moving more than this between neighbouring samples (rad) is a
configuration change, whatever the time allowed."""


def follow_branch(
    robot: RobotModel,
    q_branch: np.ndarray,
    ok: np.ndarray,
    q_prev: np.ndarray,
    multi_turn: np.ndarray,
    dt: float,
) -> tuple[np.ndarray, float] | None:
    """The joint path along one IK branch and its slowdown, or None when the branch
    leaves the limits, jumps, or would need more than the allowed slowdown.

    The fast path for linear moves: consecutive samples are one controller step
    apart (``dt`` seconds at the programmed speed), so joints with more than one
    turn of range are unwrapped by the shortest angle between neighbours.
    """
    moves = follow_branch_chain(
        robot, q_branch, ok, np.array([len(q_branch)]), q_prev, multi_turn, np.array([dt]),
        stop_at_flip=False,
    )  # fmt: skip
    return moves[0] if moves else None


def follow_branch_chain(
    robot: RobotModel,
    q_branch: np.ndarray,
    ok: np.ndarray,
    counts: np.ndarray,
    q_prev: np.ndarray,
    multi_turn: np.ndarray,
    dt: np.ndarray,
    stop_at_flip: bool = True,
) -> list[tuple[np.ndarray, float]]:
    """:func:`follow_branch` of consecutive linear moves on one branch, all at once,
    up to the first move it would refuse or that takes A5 through 0.

    Parameters
    ----------
    robot
        The robot.
    q_branch
        (m, dof) the branch's solutions at every sample of the moves, in order (radians).
    ok
        (m,) whether each is valid.
    counts
        (k,) samples per move (each at least 1, summing to m).
    q_prev
        (dof,) configuration before the first move.
    multi_turn
        (dof,) joints with more than a turn of range (unwrapped by the shortest angle).
    dt
        (k,) seconds per sample of each move at its programmed speed.
    stop_at_flip
        Whether a move that takes A5 through 0 ends the moves followed
        (:func:`follow_branch` leaves that to its caller).

    Returns
    -------
    list
        Per move, up to (not including) the first that :func:`follow_branch`
        would refuse or whose path with the configuration before it takes A5
        through 0 (:func:`~fabflow.programs.motion_checks.wrist_flips`): its joint
        path and slowdown, as :func:`follow_branch` gives them one move after the
        other (equal up to rounding: the path is summed from ``q_prev`` over the
        moves). Empty when the first move is such a move.
    """
    first = np.r_[0, np.cumsum(counts)[:-1]]
    steps = np.diff(np.vstack([q_prev, q_branch]), axis=0)
    steps[:, multi_turn] = wrap_angle(steps[:, multi_turn])
    path = q_prev + np.cumsum(steps, axis=0)
    with np.errstate(invalid="ignore"):  # invalid solutions may be NaN; they fail anyway
        load = (np.abs(steps) / (robot.velocity_limits * np.repeat(dt, counts)[:, None])).max(1)
        bad_row = (
            ~ok
            | (np.abs(steps).max(axis=1) > MAX_JOINT_STEP)
            | ~robot.within_limits(path)
            | ~np.isfinite(load)
        )
        slowdown = np.maximum(np.maximum.reduceat(np.where(bad_row, 0.0, load), first), 1.0)
    bad = np.logical_or.reduceat(bad_row, first) | (slowdown > 1.0 / MIN_SPEED_FRACTION)
    if stop_at_flip:  # A5 on both sides of zero within a move, or from the row before it
        a5 = np.r_[q_prev[4], path[:, 4]] if robot.dof > 4 else np.zeros(len(path) + 1)
        positive, negative = a5 >= A5_ZERO, a5 <= -A5_ZERO
        bad |= (np.logical_or.reduceat(positive[1:], first) | positive[first]) & (
            np.logical_or.reduceat(negative[1:], first) | negative[first]
        )
    n_good = int(np.argmax(bad)) if bad.any() else len(counts)
    if n_good == 0:
        return []
    stop = first[n_good] if n_good < len(counts) else len(path)
    # slices, not np.split: its per-piece overhead was most of a chain's time on a print path
    bounds = [0, *first[1:n_good].tolist(), int(stop)]
    paths = [path[a:b] for a, b in pairwise(bounds)]
    return list(zip(paths, slowdown[:n_good].tolist(), strict=True))
