"""Following one inverse-kinematics branch along linear moves, without a Python loop.

The fast path of :func:`fabflow.programs.feasibility.solve_moves`: consecutive
samples of a linear move are one controller step apart, so a branch that keeps
its solutions valid, its joint steps small and its speeds within the limits is
the joint path. :func:`follow_branch` follows one move; :func:`follow_branch_chain`
the linear moves after a PTP target at once (a print path's thousands of short
moves); :func:`nearest_prefix` as much of one move whose solutions change branch numbers
on the way as it can. It leaves the rest to the sample-by-sample search.
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
    dt: float,
) -> tuple[np.ndarray, float] | None:
    """The joint path along one IK branch and its slowdown, or None when the branch
    leaves the limits, jumps, or would need more than the allowed slowdown.

    The fast path for linear moves: consecutive samples are one controller step
    apart (``dt`` seconds at the programmed speed), so joints with more than one
    turn of range are unwrapped by the shortest angle between neighbours.
    """
    moves = follow_branch_chain(
        robot, q_branch, ok, np.array([len(q_branch)]), q_prev, np.array([dt]),
        stop_at_flip=False,
    )  # fmt: skip
    return moves[0] if moves else None


def follow_branch_chain(
    robot: RobotModel,
    q_branch: np.ndarray,
    ok: np.ndarray,
    counts: np.ndarray,
    q_prev: np.ndarray,
    dt: np.ndarray,
    stop_at_flip: bool = True,
) -> list[tuple[np.ndarray, float]]:
    """:func:`follow_branch` of consecutive linear moves on one branch, all at once,
    up to the first move it would refuse or that takes A5 through 0.

    Parameters
    ----------
    robot
        The robot (its multi-turn joints are unwrapped by the shortest angle).
    q_branch
        (m, dof) the branch's solutions at every sample of the moves, in order (radians).
    ok
        (m,) whether each is valid.
    counts
        (k,) samples per move (each at least 1, summing to m).
    q_prev
        (dof,) configuration before the first move.
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
    multi_turn = robot.multi_turn
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


def nearest_prefix(
    robot: RobotModel,
    q_rows: np.ndarray,
    valid_rows: np.ndarray,
    q_prev: np.ndarray,
    dt: float,
) -> tuple[np.ndarray, int]:
    """The first samples of a linear move, each taking the valid solution nearest the
    one before, as :func:`fabflow.programs.feasibility._step_through` takes them,
    without a Python loop: for a move along which the solver's branch numbers swap.

    Each step's choice depends only on the branch chosen at the sample before, so
    the choices are a table per sample (the nearest solution after each branch),
    and the branches taken are the prefix compositions of those tables, found by
    doubling (Hillis-Steele). Distances are joint steps over the robot's speed
    limits (``dt`` seconds per sample), multi-turn joints by the shortest angle.

    Parameters
    ----------
    robot
        The robot.
    q_rows
        (m, K, dof) every branch's solution at each sample (radians).
    valid_rows
        (m, K) which exist within the limits.
    q_prev
        (dof,) configuration before the move.
    dt
        Seconds per sample at the programmed speed.

    Returns
    -------
    path, branch
        The joint path (k, dof) of the first k samples, equal up to rounding to the
        sample-by-sample search's, and the branch at the last of them (-1 when k is
        0). It stops before the first sample where that search does more than take
        the nearest solution: one with no solution, a step over the speed limits
        (there it solves the sample again near the one before, as at the wrist
        singularity), a jump over :data:`MAX_JOINT_STEP` or a path leaving the
        limits.
    """
    m, K = valid_rows.shape
    if m == 0:
        return np.zeros((0, len(q_prev))), -1
    # steps from every branch at a sample (and from q_prev) to every branch at the next
    before = np.concatenate([np.broadcast_to(q_prev, (1, K, len(q_prev))), q_rows[:-1]])
    steps = q_rows[:, None, :, :] - before[:, :, None, :]  # (m, K from, K to, dof)
    multi_turn = robot.multi_turn
    steps[..., multi_turn] = wrap_angle(steps[..., multi_turn])
    with np.errstate(invalid="ignore"):  # invalid solutions may be NaN; masked below
        load = (np.abs(steps) / (robot.velocity_limits * dt)).max(axis=-1)
    load = np.where(valid_rows[:, None, :], load, np.inf)
    table = np.argmin(load, axis=2)  # (m, K): the branch taken after each branch
    shift = 1
    while shift < m:  # prefix compositions: table[j] becomes the choice from q_prev
        table[shift:] = np.take_along_axis(table[shift:], table[:-shift], axis=1)
        shift *= 2
    chosen = table[:, 0]
    came_from = np.r_[0, chosen[:-1]]
    rows = np.arange(m)
    taken = steps[rows, came_from, chosen]
    path = q_rows[rows, chosen]
    path[:, multi_turn] = q_prev[multi_turn] + np.cumsum(taken[:, multi_turn], axis=0)
    with np.errstate(invalid="ignore"):
        bad = ~(load[rows, came_from, chosen] <= 1.0)  # also where no solution exists
        bad |= np.abs(taken).max(axis=1) > MAX_JOINT_STEP
    bad |= ~robot.within_limits(path)
    k = int(np.argmax(bad)) if bad.any() else m
    return path[:k], int(chosen[k - 1]) if k else -1
