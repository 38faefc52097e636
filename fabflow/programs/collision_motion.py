"""The moves of a program as the collision check sees them (:mod:`fabflow.programs.collision`).

Per move: the stage (which obstacles stand), the block held, whether it is a
seat move, and the samples: linear-move samples and the first target as they
are, PTP moves as joint interpolations with a bound of the body travel. Also
what a move's check depends on (:func:`move_keys`), so that a re-planning round
checks only the moves it changed (:func:`only_moves`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from fabflow.programs.ir import Move, Program, SetOutput
from fabflow.robots.chain import RobotModel

SEAT_HEIGHT = 0.001
"""A linear move ending within this height of the place's is on the bed (metres)."""

CheckMemo = dict[tuple[object, ...], Sequence[tuple[int, int, float]]]
"""Per move key (:func:`move_keys`), the move's contacts: ``(body, obstacle, distance)``."""


@dataclass(frozen=True)
class CheckMotion:
    """A program's moves for the check: what holds per move, and the samples.

    ``fixed_*`` are samples checked as they are (linear-move samples, the first
    target); ``ptp_*`` describe each PTP move for the coarse-to-fine sampling.
    """

    moves: list[Move]
    stage: np.ndarray  # (M,) obstacles with since < stage are present
    held: list[str | None]  # (M,) block held during each move
    seat: np.ndarray  # (M,) the held block's seat move
    fixed_q: np.ndarray  # (F, dof)
    fixed_move: np.ndarray  # (F,)
    ptp_move: np.ndarray  # (P,)
    ptp_q0: np.ndarray  # (P, dof)
    ptp_q1: np.ndarray  # (P, dof)
    ptp_travel: np.ndarray  # (P,) first-order body travel bound (metres)
    ptp_step: np.ndarray  # (P,) largest joint change (radians)


def _lever_arms(
    robot: RobotModel, q: np.ndarray, T_flange_tool: np.ndarray, reach_beyond: float
) -> np.ndarray:
    """(M, dof) distance of the farthest body point from each joint axis at each target (m).

    The points are the frame origins and the TCP; ``reach_beyond`` (metres) covers
    the capsule radii and a held block around them.
    """
    F = robot.frames(q)
    tcp = F[:, -1, :3, :3] @ T_flange_tool[:3, 3] + F[:, -1, :3, 3]
    points = np.concatenate([F[:, :, :3, 3], tcp[:, None]], axis=1)  # (M, P, 3)
    origin = F[:, : robot.dof, None, :3, 3]  # joint j turns about z of frame j
    axis = F[:, : robot.dof, None, :3, 2]
    rel = points[:, None] - origin
    along = np.sum(rel * axis, axis=-1, keepdims=True)
    return np.linalg.norm(rel - along * axis, axis=-1).max(axis=-1) + reach_beyond


def program_motion(program: Program, robot: RobotModel, reach_beyond: float) -> CheckMotion:
    """The moves of a program, with stage, held block and seat flag per move.

    ``reach_beyond`` bounds how far a body reaches past the frame origins and the
    TCP (metres), for the lever arms of :func:`_lever_arms`.
    """
    moves: list[Move] = []
    grip_at: dict[int, str | None] = {}
    last_move: dict[str, int] = {}
    released: dict[str | None, int] = {}
    for ins in program.instructions:
        if isinstance(ins, Move):
            moves.append(ins)
            if ins.element is not None:
                last_move[ins.element] = len(moves)
        elif isinstance(ins, SetOutput) and ins.name == "gripper":
            if ins.value:
                grip_at[len(moves)] = ins.element
            else:
                released[ins.element] = len(moves)
    # An element is complete from its release on, else after its last move.
    complete = np.sort([released.get(e, last) for e, last in last_move.items()])
    release = set(released.values())
    targets = np.array([m.q for m in moves], dtype=float).reshape(len(moves), robot.dof)
    T_flange_tool = np.asarray(program.T_flange_tool, dtype=float)
    fixed: list[np.ndarray] = []
    fixed_move: list[int] = []
    ptp: list[int] = []
    held_of: list[str | None] = []
    seat: list[bool] = []
    held: str | None = None
    for i, move in enumerate(moves):
        held = grip_at.get(i, held)
        if i in release:
            held = None
        if move.kind == "lin" and move.via_q is not None:
            fixed.append(np.vstack([move.via_q, targets[i][None]]))
            fixed_move += [i] * (len(move.via_q) + 1)
        elif i > 0 and move.kind == "ptp":
            ptp.append(i)
        else:
            fixed.append(targets[i][None])
            fixed_move.append(i)
        held_of.append(held)
        seat.append(held is not None and move.kind == "lin" and i in grip_at)
    # down onto the bed: the linear moves right before a release that end at the
    # place's height (the place, and the lowering beside it of a block slid in),
    # or a descent straight down made a joint move (through the wrist singularity)
    for i in release:
        z_place = moves[i - 1].T_world_tool[2, 3]
        k = i - 1
        while k >= 0 and held_of[k] is not None:
            down = moves[k].kind != "lin"
            if down and not _straight_down(moves, k):
                break
            if abs(moves[k].T_world_tool[2, 3] - z_place) > SEAT_HEIGHT:
                break
            seat[k] = True
            if down:  # the way down ends the way onto the bed
                break
            k -= 1
    # stage 2c - 1 for the moves of the c-th completed element after its completion
    # (its retract), 2c from the next element's first move (see
    # fabflow.programs.collision_model): what comes by hand waits for the tool to leave
    done_at = {e: released.get(e, last) for e, last in last_move.items()}
    own_done = np.array(
        [m.element is not None and done_at[m.element] <= i for i, m in enumerate(moves)],
        dtype=bool,
    )
    p = np.array(ptp, dtype=np.intp)
    # the lever arms at the ends of the joint moves alone (a print path has thousands
    # of linear moves and a few joint moves)
    ends = np.unique(np.r_[p - 1, p])
    arms = np.zeros((len(moves), robot.dof))
    if len(ends):
        arms[ends] = _lever_arms(robot, targets[ends], T_flange_tool, reach_beyond)
    dq = np.abs(targets[p] - targets[p - 1])
    lever = np.maximum(arms[p - 1], arms[p])
    return CheckMotion(
        moves=moves,
        # never back: a HOME move between two moves of one block keeps what came
        stage=np.maximum.accumulate(
            2 * np.searchsorted(complete, np.arange(len(moves)), side="right") - own_done
        ),
        held=held_of,
        seat=np.array(seat, dtype=bool),
        fixed_q=np.vstack(fixed) if fixed else np.zeros((0, robot.dof)),
        fixed_move=np.array(fixed_move, dtype=np.intp),
        ptp_move=p,
        ptp_q0=targets[p - 1],
        ptp_q1=targets[p],
        ptp_travel=np.sum(dq * lever, axis=1),
        ptp_step=dq.max(axis=1, initial=0.0),
    )


def _straight_down(moves: Sequence[Move], k: int) -> bool:
    """Whether move ``k`` takes the tool straight down from where the move before ended
    (within :data:`SEAT_HEIGHT` horizontally)."""
    if k == 0:
        return False
    start, end = moves[k - 1].T_world_tool[:3, 3], moves[k].T_world_tool[:3, 3]
    return bool(np.hypot(*(end[:2] - start[:2])) <= SEAT_HEIGHT and end[2] < start[2])


def move_keys(motion: CheckMotion, parts: Mapping[str, str]) -> list[tuple[object, ...]]:
    """Per move, everything its collision check depends on besides the obstacles,
    the robot, the tool and the clearance: its samples (a PTP move's two ends),
    the block it holds, its seat flag, its stage and its part.

    Two moves with equal keys in programs checked against the same obstacles,
    robot, tool and clearance have the same contacts.
    """
    keys: list[tuple[object, ...]] = []
    # fixed samples come in move order: split them where the move changes
    cut = np.flatnonzero(np.diff(motion.fixed_move)) + 1
    of_move = motion.fixed_move[np.r_[0, cut]].tolist() if len(motion.fixed_move) else []
    bounds = [0, *cut.tolist(), len(motion.fixed_q)]
    rows = pairwise(bounds)
    samples = dict(zip(of_move, (motion.fixed_q[a:b].tobytes() for a, b in rows), strict=True))
    # a PTP move's two ends, (2, dof) in C order: the row of both
    both = np.concatenate([motion.ptp_q0, motion.ptp_q1], axis=1)
    ends = dict(zip(motion.ptp_move.tolist(), (e.tobytes() for e in both), strict=True))
    for i, move in enumerate(motion.moves):
        keys.append(
            (
                i in ends,
                ends[i] if i in ends else samples[i],
                motion.held[i],
                bool(motion.seat[i]),
                int(motion.stage[i]),
                parts.get(move.element, move.element) if move.element is not None else None,
            )
        )
    return keys


def only_moves(motion: CheckMotion, keep: np.ndarray) -> CheckMotion:
    """``motion`` with the samples of the moves ``keep`` ((M,) bool) alone."""
    fixed, ptp = keep[motion.fixed_move], keep[motion.ptp_move]
    return dataclasses.replace(
        motion,
        fixed_q=motion.fixed_q[fixed],
        fixed_move=motion.fixed_move[fixed],
        ptp_move=motion.ptp_move[ptp],
        ptp_q0=motion.ptp_q0[ptp],
        ptp_q1=motion.ptp_q1[ptp],
        ptp_travel=motion.ptp_travel[ptp],
        ptp_step=motion.ptp_step[ptp],
    )
