"""What a robot programmer checks in a program's joint values before running it.

Three figures, computed from the joint configuration ``q`` of every move
(the values the writers turn into targets, the JSON stream carries them as is):

* **Configuration** of each target: the branch of the closed-form inverse
  kinematics it lies on (shoulder front/back, elbow up/down, wrist flipped or
  not; KUKA's Status S, ABB's cfx), found by solving the target's own flange
  pose again and matching the branches (:func:`configuration_of`).
* **Needless swings**: a PTP move in which A2 or A3 turns by more than
  :data:`SWING_MAIN_AXIS_DEG`, or A1 turns more than :data:`SWING_A1_EXCESS_DEG`
  beyond the change of the wrist centre's azimuth about A1 — an arm folding
  over or turning around where a short motion reaches the same point
  (:func:`needless_swings`).
* **Configuration changes**: between consecutive targets, and inside a linear
  move (which a controller refuses); :func:`program_checks` sums them up per
  program.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fabflow.robots.chain import RobotModel
from fabflow.tasks.targets import SWING_MAIN_AXIS_DEG

SWING_A1_EXCESS_DEG = 30.0
"""A PTP turning A1 this much (degrees) more than the wrist centre moves about it turns around."""
_SAME_ANGLE = 1e-4
"""Two joint values closer than this (radians, modulo a turn) are the same branch."""
A5_ZERO = 5e-10
"""A5 values closer to 0 than this (radians) have no sign (at the singularity)."""
_WRIST_FRAME = 4
"""Index in :meth:`RobotModel.frames` of the frame at the wrist centre (DH frame 4)."""


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles (radians) wrapped into [-pi, pi)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def configuration_of(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    """The inverse-kinematics branch each configuration lies on.

    Parameters
    ----------
    robot
        A robot with closed-form inverse kinematics.
    q
        ``(n, dof)`` joint values (radians).

    Returns
    -------
    numpy.ndarray
        ``(n,)`` branch numbers (``-1`` where none matches, which happens only
        for a pose the solver cannot reproduce). At a wrist singularity (A5 at
        0) the two wrist branches meet; the lower number is returned.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    if len(q) == 0:
        return np.zeros(0, dtype=np.intp)
    q_all, _ = robot.ik_batch(robot.fk(q), q_ref=q)
    close = (np.abs(wrap_angle(q_all - q[:, None, :])) < _SAME_ANGLE).all(axis=2) & np.isfinite(
        q_all
    ).all(axis=2)
    branch = np.argmax(close, axis=1)
    return np.where(close.any(axis=1), branch, -1)


def wrist_azimuth(robot: RobotModel, q: np.ndarray) -> np.ndarray:
    """Azimuth (radians) of the wrist centre about the base z axis, ``(n,)``."""
    centre = robot.frames(np.atleast_2d(q))[:, _WRIST_FRAME, :3, 3]
    return np.arctan2(centre[:, 1], centre[:, 0])


def needless_swings(robot: RobotModel, q_from: np.ndarray, q_to: np.ndarray) -> np.ndarray:
    """Which joint moves swing the arm needlessly (see the module docstring).

    Parameters
    ----------
    robot
        The robot (A1 about the base z axis).
    q_from, q_to
        ``(n, dof)`` joint values at the start and end of each move (radians).

    Returns
    -------
    numpy.ndarray
        ``(n,)`` bool.
    """
    q_from = np.atleast_2d(q_from)
    q_to = np.atleast_2d(q_to)
    if len(q_from) == 0:
        return np.zeros(0, dtype=bool)
    turn = np.abs(q_to - q_from)
    main = (turn[:, 1:3] > np.radians(SWING_MAIN_AXIS_DEG)).any(axis=1)
    azimuth = np.abs(wrap_angle(wrist_azimuth(robot, q_to) - wrist_azimuth(robot, q_from)))
    around = turn[:, 0] > azimuth + np.radians(SWING_A1_EXCESS_DEG)
    return main | around


def avoidable_swings(
    robot: RobotModel, q_from: np.ndarray, T_base_flange_to: np.ndarray
) -> np.ndarray:
    """Which moves have a target configuration that is not a swing from ``q_from``.

    Parameters
    ----------
    robot
        A robot with closed-form inverse kinematics.
    q_from
        ``(n, dof)`` joint values at the start of each move (radians).
    T_base_flange_to
        ``(n, 4, 4)`` the flange pose each move goes to (base frame, metres).

    Returns
    -------
    numpy.ndarray
        ``(n,)`` bool: some valid configuration of the target (any branch, A1
        at either end of its range where both are within the limits) is reached
        without a swing (:func:`needless_swings`).
    """
    q_from = np.atleast_2d(q_from)
    n = len(q_from)
    if n == 0:
        return np.zeros(0, dtype=bool)
    q_all, valid = robot.ik_batch(T_base_flange_to, q_ref=q_from)
    k = q_all.shape[1]
    other = q_all.copy()
    other[..., 0] -= 2.0 * np.pi * np.sign(other[..., 0])
    lo, hi = robot.joint_limits[0]
    other_ok = valid & (other[..., 0] >= lo) & (other[..., 0] <= hi)
    options = np.concatenate([q_all, other], axis=1).reshape(-1, robot.dof)
    ok = np.concatenate([valid, other_ok], axis=1)
    swing = needless_swings(robot, np.repeat(q_from, 2 * k, axis=0), options)
    return (ok & ~swing.reshape(n, 2 * k)).any(axis=1)


def wrist_flips(q_path: np.ndarray) -> bool:
    """Whether A5 changes sign along a joint path ``(k, dof)`` (the wrist configuration flips)."""
    a5 = q_path[:, 4]
    return bool((a5 >= A5_ZERO).any() and (a5 <= -A5_ZERO).any())


def program_checks(
    robot: RobotModel,
    kinds: Sequence[str],
    q: np.ndarray,
    via_q: Sequence[np.ndarray | None],
    T_base_flange: np.ndarray | None = None,
    joint: np.ndarray | None = None,
    config: np.ndarray | None = None,
) -> dict[str, Any]:
    """The configuration figures of one program's moves.

    Parameters
    ----------
    robot
        The robot.
    kinds
        ``"ptp"`` or ``"lin"`` per move, in order.
    q
        ``(n, dof)`` joint values at each move's target (radians).
    via_q
        Per move, the joint samples inside a linear move (or None).
    T_base_flange
        ``(n, 4, 4)`` flange pose of each move's target (base frame, metres);
        with it, the swings another configuration of the target would have
        avoided are counted (``avoidable_swings``).
    joint
        ``(n,)`` bool: joint moves (HOME on the way between two configurations).
        They count for swings, not as targets whose configuration changes.
    config
        ``(n,)`` :func:`configuration_of` ``q``, when the caller has it already.

    Returns
    -------
    dict
        ``moves``, ``ptp_moves``, ``needless_swings`` (count) and
        ``swing_moves`` (their indices), ``avoidable_swings`` (or None),
        ``configuration_changes`` between
        consecutive targets, ``configurations`` (the distinct branches used),
        and ``changes_inside_lin`` (linear moves whose configuration changes) and
        ``inside_lin_moves`` (their indices).
    """
    q = np.asarray(q, dtype=float)
    ptp = np.array([k == "ptp" for k in kinds], dtype=bool)
    n = len(q)
    swing = np.zeros(n, dtype=bool)
    if n > 1:
        swing[1:] = needless_swings(robot, q[:-1], q[1:]) & ptp[1:]
    avoidable = None
    if T_base_flange is not None:
        moves = np.flatnonzero(swing)
        avoidable = int(avoidable_swings(robot, q[moves - 1], T_base_flange[moves]).sum())
    cartesian = np.ones(n, dtype=bool) if joint is None else ~np.asarray(joint, dtype=bool)
    config = configuration_of(robot, q) if config is None else np.asarray(config)
    targets = config[cartesian]
    changes = int((targets[1:] != targets[:-1]).sum()) if len(targets) > 1 else 0
    # linear moves whose wrist flips (A5 changes sign) or whose configuration changes;
    # the ends of all at once (28,000 moves on a print wall), the few with samples each
    lin = np.flatnonzero(~ptp[1:]) + 1
    a5 = q[:, 4]
    ends_high, ends_low = np.maximum(a5[lin - 1], a5[lin]), np.minimum(a5[lin - 1], a5[lin])
    flips = (ends_high >= A5_ZERO) & (ends_low <= -A5_ZERO)
    for j, k in enumerate(lin.tolist()):
        if via_q[k] is not None:
            flips[j] = wrist_flips(np.vstack([q[k - 1], via_q[k], q[k]]))
    inside = lin[flips | (config[lin] != config[lin - 1])].tolist()
    return {
        "moves": n,
        "ptp_moves": int(ptp.sum()),
        "needless_swings": int(swing.sum()),
        "swing_moves": np.flatnonzero(swing).tolist(),
        "avoidable_swings": avoidable,
        "configuration_changes": changes,
        "configurations": sorted({int(c) for c in targets}),
        "changes_inside_lin": len(inside),
        "inside_lin_moves": inside,
    }
