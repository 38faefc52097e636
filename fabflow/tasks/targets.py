"""Tool target poses of elements, in the world frame.

* Block: the tool centre point (TCP) sits at the centre of the block's top face,
  tool z points down (into the block), tool x runs along the block's length.
* Print path: its tool frames (:func:`fabflow.design.print_path.element_tool_frames`:
  one per waypoint, tool z pointing down, x along the path). The element's
  *target* (the one stored in a work package) is the first frame.
* Task point: the element frame itself is the tool frame to reach.

All poses are 4x4 matrices in metres; ``T_world_tool``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fabflow.design.elements import Element
from fabflow.design.print_path import element_tool_frames as print_path_tool_frames
from fabflow.project import Project
from fabflow.robots.catalog import get_robot
from fabflow.transforms.so3 import R_FLIP_X

SWING_MAIN_AXIS_DEG = 90.0
"""A PTP turning A2 or A3 by more than this (degrees) swings the arm over: counted in
the programs (:mod:`fabflow.programs.motion_checks`) and avoided by the lift choice
(:mod:`fabflow.tasks.awkward_lifts`)."""


def element_tool_frames(element: Element) -> np.ndarray:
    """Every tool frame the robot must reach to build ``element``.

    Parameters
    ----------
    element
        A block, print path or task point.

    Returns
    -------
    np.ndarray
        (k, 4, 4) tool poses in the world frame (metres), k >= 1.
    """
    T_world_element = np.asarray(element.T_world_element, dtype=float)
    if element.type == "block":
        height = 0.0 if element.extents is None else float(np.asarray(element.extents)[2])
        T = T_world_element.copy()
        T[:3, :3] = T_world_element[:3, :3] @ R_FLIP_X
        T[:3, 3] = T_world_element[:3, 3] + T_world_element[:3, 2] * (0.5 * height)
        return T[None]
    if element.type == "print_path" and element.polyline is not None:
        return print_path_tool_frames(element)
    return T_world_element[None].copy()


def tool_frames(elements: Sequence[Element]) -> tuple[np.ndarray, np.ndarray]:
    """All tool frames of many elements, flattened (blocks are handled in one batch).

    Returns
    -------
    T_world_tool
        (K, 4, 4) tool poses in the world frame (metres).
    owner
        (K,) index of the element each frame belongs to; non-decreasing, every
        element owns at least one frame.
    """
    n = len(elements)
    if n == 0:
        return np.zeros((0, 4, 4)), np.zeros(0, dtype=np.intp)
    is_block = np.array([e.type == "block" for e in elements])
    blocks = np.flatnonzero(is_block)
    parts: list[np.ndarray] = []
    owners: list[np.ndarray] = []
    if len(blocks):
        T_we = np.stack([np.asarray(elements[i].T_world_element, dtype=float) for i in blocks])
        height = np.array(
            [0.0 if elements[i].extents is None else elements[i].extents[2] for i in blocks],
            dtype=float,
        )
        T = T_we.copy()
        T[:, :3, :3] = T_we[:, :3, :3] @ R_FLIP_X
        T[:, :3, 3] += T_we[:, :3, 2] * (0.5 * height)[:, None]
        parts.append(T)
        owners.append(blocks)
    for i in np.flatnonzero(~is_block):
        f = element_tool_frames(elements[i])
        parts.append(f)
        owners.append(np.full(len(f), i))
    T_all = np.concatenate(parts)
    owner = np.concatenate(owners)
    order = np.argsort(owner, kind="stable")
    return T_all[order], owner[order]


def approach_poses(T_world_tool: np.ndarray, along_tool: np.ndarray, distance: float) -> np.ndarray:
    """Poses ``distance`` metres before tool targets, where the robot approaches them from.

    Blocks and print paths are approached from above (world z); task points
    (``along_tool``) back along their tool z axis. The programs move through
    these poses and the planner checks they are reachable.

    Parameters
    ----------
    T_world_tool
        (..., 4, 4) tool targets in the world (metres).
    along_tool
        (...) bool: approach along the tool axis instead of from above.
    distance
        Approach distance (metres).
    """
    T = np.array(T_world_tool, dtype=float, copy=True)
    along = np.asarray(along_tool, dtype=bool)
    T[..., 2, 3] += np.where(along, 0.0, distance)
    T[..., :3, 3] -= along[..., None] * T[..., :3, 2] * distance
    return T


def T_base_pick_tool(project: Project) -> np.ndarray:
    """Tool pose for gripping a block in the platform magazine, in the robot base frame.

    ``robot.platform.T_platform_pick`` is the centre of the top face of the block
    waiting in the magazine (z up); the magazine rides on the lift with the arm.
    """
    platform = project.robot.platform
    T_platform_base = platform.T_platform_base.matrix()
    T_pick = np.linalg.inv(T_platform_base) @ platform.T_platform_pick.matrix()
    T_pick[:3, :3] = T_pick[:3, :3] @ R_FLIP_X
    return T_pick


def home_configuration(project: Project) -> np.ndarray:
    """The HOME joint configuration (radians): ``robot.home_deg`` or the robot's own."""
    robot = get_robot(project.robot.name)
    if project.robot.home_deg is not None:
        return robot.from_deg(project.robot.home_deg)
    return np.asarray(robot.q_home, dtype=float)


def T_base_home_tool(project: Project) -> np.ndarray:
    """Tool pose at HOME, in the robot base frame (metres)."""
    robot = get_robot(project.robot.name)
    return robot.fk(home_configuration(project)) @ project.robot.tool.T_flange_tool.matrix()


APPROACH_MARGIN = 0.005
"""Added to a block's height and twice the clearance for its approach distance (metres)."""


def block_approach(element: Element, project: Project) -> float:
    """Approach and retract distance of a block (metres).

    ``program.approach`` is a minimum: a held block arriving above its place must
    clear the neighbours of its course, which stand as high as itself, so the
    distance is at least the block's height plus twice ``program.clearance``
    (the clearance kept, and the same again for the blending and the parking
    error of the arrival) plus :data:`APPROACH_MARGIN`.
    """
    settings = project.program
    height = 0.0 if element.extents is None else float(np.asarray(element.extents)[2])
    return max(settings.approach, height + 2.0 * settings.clearance + APPROACH_MARGIN)


def element_targets(elements: Sequence[Element]) -> np.ndarray:
    """One tool target per element (the first of :func:`element_tool_frames`).

    Returns
    -------
    np.ndarray
        (N, 4, 4) tool poses in the world frame (metres).
    """
    T, owner = tool_frames(elements)
    if len(owner) == 0:
        return T
    first = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    return T[first]
