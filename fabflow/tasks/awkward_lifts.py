"""Lift levels at which a block is awkward to build from a station, and the reach without them.

A station reaches a block at several lift heights. At some of them the arm
can only build it awkwardly:

* **singular**: the block's straight descent onto its place takes A5 through 0
  (or within :data:`SINGULAR_MARGIN_DEG` of it) on every inverse kinematics
  branch that follows the whole descent and also reaches the magazine (a
  block's motion keeps one configuration). A controller refuses a linear move
  through A5 = 0, and a joint move through it changes the wrist's status twice
  (down and back up).
* **swinging**: on every branch left, A2 or A3 turns more than
  :data:`~fabflow.tasks.targets.SWING_MAIN_AXIS_DEG` less
  :data:`SWING_MARGIN_DEG` from the pick approach at the magazine to the
  travel point above the block at the pick height, or from there to the
  block's approach pose along the plain route (no raised approach, no tuck):
  the A2/A3 part of the programs' wide swing
  (:mod:`fabflow.programs.motion_checks`).

A descent that stays clear of that margin is no trouble: straight down with the
tool pointing down, A1, A4 and A6 stand still and only A2, A3 and A5 turn.

:func:`prefer_regular` takes these levels out of the reach matrix of the
chosen stations: the singular levels wherever another level, at the same
station or another one, reaches the block; then the swinging ones wherever
another level of the same station reaches it. The build order and the lift of
every visit then follow from what is left.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import sparse

from fabflow.design.elements import Element
from fabflow.project import Project
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.robots.platform import T_world_base
from fabflow.tasks.targets import (
    SWING_MAIN_AXIS_DEG,
    T_base_pick_tool,
    block_approach,
    element_targets,
)

DESCENT_SAMPLES = 9
"""Points along a block's descent checked for the wrist singularity."""
SINGULAR_MARGIN_DEG = 4.0
"""A descent with A5 closer to 0 than this counts as singular: the platform parks a
few centimetres off its plan, which moves A5 by a few degrees there."""
SWING_MARGIN_DEG = 5.0
"""A turn of A2 or A3 within this of a wide swing counts as one, for the same reason."""
_CHUNK = 4096
"""(station, block, level) cases solved at once: bounds the memory of the batched inverse
kinematics."""


def awkward_levels(
    project: Project,
    T_world_platform: np.ndarray,
    lifts: np.ndarray,
    work: Sequence[Element],
    station: np.ndarray,
    element: np.ndarray,
    reach: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The lift levels at which each (station, element) pair is singular and swinging.

    Parameters
    ----------
    project
        The project (robot, tool, platform mounting, magazine, approach settings).
    T_world_platform
        ``(k, 4, 4)`` platform poses of the stations (world frame, metres).
    lifts
        ``(L,)`` lift levels (metres).
    work
        The robot-built elements.
    station, element
        ``(P,)`` indices of the pairs into ``T_world_platform`` and ``work``.
    reach
        ``(P,)`` int64 bit masks over ``lifts``: the levels at which the station
        reaches the element, the only ones looked at.

    Returns
    -------
    tuple of numpy.ndarray
        Two ``(P,)`` int64 bit masks over ``lifts`` (bit ``l``: singular,
        swinging at level ``l``); 0 for elements that are not blocks, and for
        every pair when the robot has not six axes.
    """
    station = np.asarray(station, dtype=np.intp)
    element = np.asarray(element, dtype=np.intp)
    reach = np.asarray(reach, dtype=np.int64)
    masks = np.zeros((2, len(station)), dtype=np.int64)
    robot = get_robot(project.robot.name)
    is_block = np.array([work[e].type == "block" for e in element], dtype=bool)
    if robot.dof != 6 or not is_block.any():
        return masks[0], masks[1]
    T_tool_flange = np.linalg.inv(project.robot.tool.T_flange_tool.matrix())
    T_base_world = np.linalg.inv(
        T_world_base(
            np.asarray(T_world_platform, dtype=float)[:, None],
            np.asarray(lifts, dtype=float)[None, :],
            project.robot.platform.T_platform_base.matrix(),
        )
    )  # (k, L, 4, 4)
    T_pick = T_base_pick_tool(project)
    _, at_pick = robot.ik_batch((T_pick @ T_tool_flange)[None])
    # the cases: (pair, level) where the station reaches a block
    level_bits = np.int64(1) << np.arange(len(lifts), dtype=np.int64)
    pair, level = np.nonzero((reach[:, None] & level_bits[None]) != 0)
    keep = is_block[pair]
    pair, level = pair[keep], level[keep]
    if len(pair) == 0:
        return masks[0], masks[1]
    # the place and approach of every block concerned, once each
    blocks, slot = np.unique(element[pair], return_inverse=True)
    T_place = element_targets([work[e] for e in blocks])[slot.ravel()]
    up = np.array([block_approach(work[e], project) for e in blocks])[slot.ravel()]
    for chunk in np.array_split(np.arange(len(pair)), max(1, -(-len(pair) // _CHUNK))):
        p, lv = pair[chunk], level[chunk]
        flags = _case_flags(
            robot, T_base_world[station[p], lv], T_place[chunk], up[chunk], T_tool_flange,
            T_pick, at_pick[0],
        )  # fmt: skip
        for m in range(2):
            np.add.at(masks[m], p, np.where(flags[m], level_bits[lv], 0))
    return masks[0], masks[1]


def _case_flags(
    robot: RobotModel,
    T_base_world: np.ndarray,
    T_place: np.ndarray,
    up: np.ndarray,
    T_tool_flange: np.ndarray,
    T_pick: np.ndarray,
    at_pick: np.ndarray,
) -> np.ndarray:
    """Singular and swinging flags of C cases, each a block seen from a station's base.

    Parameters
    ----------
    robot
        The arm (closed-form inverse kinematics).
    T_base_world
        ``(C, 4, 4)`` inverse of the arm base pose of each case (metres).
    T_place, up
        ``(C, 4, 4)`` tool at the block's place (world frame, metres) and ``(C,)``
        its approach distance above it (metres).
    T_tool_flange
        4x4 flange in the tool frame.
    T_pick
        4x4 tool at the magazine's pick in the arm base frame (it rides on the lift).
    at_pick
        ``(K,)`` which inverse kinematics branches reach the pick.

    Returns
    -------
    numpy.ndarray
        ``(2, C)`` bool: singular (no branch that reaches the pick follows the
        whole descent clear of A5 = 0; this includes a case no branch follows at
        all), and swinging.
    """
    n = len(T_place)
    frac = np.linspace(0.0, 1.0, DESCENT_SAMPLES)
    # the tool from its approach pose down to the place, in the base: (C, S, 4, 4)
    T_path = np.repeat(T_place[:, None], DESCENT_SAMPLES, axis=1)
    T_path[..., 2, 3] += up[:, None] * frac[None, ::-1]
    T = T_base_world[:, None] @ T_path @ T_tool_flange
    # only the arm branches that reach the pick (a block's motion keeps one) are solved
    arms = np.flatnonzero(at_pick) % 4 if robot.opw is not None else None
    q, valid = robot.ik_batch(T.reshape(-1, 4, 4), arms=arms)
    shape = (n, DESCENT_SAMPLES, valid.shape[-1])
    a5 = q[..., 4].reshape(shape)
    valid = valid.reshape(shape).all(axis=1) & at_pick  # the whole descent and the pick
    flips = (np.sign(a5) != np.sign(a5[:, :1])).any(axis=1)
    flips |= (np.abs(a5) < np.radians(SINGULAR_MARGIN_DEG)).any(axis=1)
    # a level the reach model grants but no branch follows is no better than a singular one
    singular = ~(valid & ~flips).any(axis=-1)
    # the pick approach, the travel point above the block at its height (where the
    # block comes from below it) and the approach pose (the descent's first sample)
    # blocks share a few approach distances: one pick approach each
    ups, which = np.unique(up, return_inverse=True)
    T_pick_up = np.repeat(T_pick[None], len(ups), axis=0)
    T_pick_up[:, 2, 3] += ups
    q_pick = robot.ik_batch(T_pick_up @ T_tool_flange)[0][which.ravel()]  # (C, branch, dof)
    T_up = T[:, 0] @ np.linalg.inv(T_tool_flange)  # (C, 4, 4) tools at the approach pose
    T_travel = T_up.copy()
    T_travel[:, 2, 3] = np.maximum(T_up[:, 2, 3], T_pick_up[which.ravel(), 2, 3])
    q_travel, _ = robot.ik_batch(T_travel @ T_tool_flange, arms=arms)
    q_up = q.reshape(n, DESCENT_SAMPLES, -1, robot.dof)[:, 0]  # (C, branch, dof)
    turn = np.maximum(
        np.abs(q_travel[..., 1:3] - q_pick[..., 1:3]).max(axis=-1),
        np.abs(q_up[..., 1:3] - q_travel[..., 1:3]).max(axis=-1),
    )
    turn = np.where(np.isfinite(turn), turn, np.inf)
    calm = valid & ~flips & (turn <= np.radians(SWING_MAIN_AXIS_DEG - SWING_MARGIN_DEG))
    swinging = (valid & ~flips).any(axis=-1) & ~calm.any(axis=-1)
    return np.stack([singular, swinging])


def prefer_regular(
    A: sparse.csr_matrix, singular: np.ndarray, swinging: np.ndarray
) -> sparse.csr_matrix:
    """The reach matrix without the awkward levels of every element that has another.

    Parameters
    ----------
    A
        ``(k, n)`` reach of the chosen stations: bit ``l`` of entry ``(s, e)`` set
        where station ``s`` reaches element ``e`` at lift level ``l``.
    singular
        Bit mask over the entries of ``A.tocoo()``, in its order: taken out of an
        element's reach where some level of some station is left, so a block
        singular at every level of its station moves to another station.
    swinging
        Bit mask over the same entries: taken out of an entry where another level
        of the same station is left (the build order across stations stays).

    Returns
    -------
    scipy.sparse.csr_matrix
        The same shape; a station that reaches an element only at singular
        levels no longer reaches it, where another does.
    """
    coo = A.tocoo()
    if len(np.ravel(singular)) != A.nnz or len(np.ravel(swinging)) != A.nnz:
        raise ValueError("prefer_regular needs one singular and one swinging mask per entry")
    if A.nnz and len(np.unique(coo.row * A.shape[1] + coo.col)) != A.nnz:
        raise ValueError("prefer_regular needs a reach matrix without repeated entries")
    data = coo.data.astype(np.int64)
    regular = data & ~np.asarray(singular, dtype=np.int64)
    kept = np.zeros(A.shape[1], dtype=bool)
    kept[coo.col[regular != 0]] = True
    data = np.where(kept[coo.col], regular, data)
    calm = data & ~np.asarray(swinging, dtype=np.int64)
    data = np.where(calm != 0, calm, data)
    out = sparse.csr_matrix((data, (coo.row, coo.col)), shape=A.shape)
    out.eliminate_zeros()
    return out
