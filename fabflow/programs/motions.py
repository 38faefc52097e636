"""Motions per element type, as Cartesian tool waypoints in the world frame.

* Block (pick and place): approach above the pick frame, linear down, grip,
  retract, travel at safe height (the pick approach height, where the arm
  reaches it above the place pose), approach above the place pose, linear
  down, release, retract. The pick frame is on the platform (a block magazine), so it
  is given in the robot base frame and placed in the world with the station's
  localized base pose.
* Print path: approach above the first frame, linear down, extruder on, linear
  moves through every frame at the print speed with blending, extruder off,
  retract.
* Task point: approach along the tool axis, linear to the point, action output
  on, dwell, off, linear retract.

Every waypoint is a tool pose ``T_world_tool`` (4x4, metres).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fabflow.design.elements import Element
from fabflow.project import Project
from fabflow.tasks.targets import approach_poses, element_tool_frames
from fabflow.transforms.so3 import R_FLIP_X

OUTPUTS = {"gripper": 1, "extruder": 2, "drill": 3, "mark": 4, "measure": 5}
"""Digital output numbers of the tool actions."""

GRIP_DWELL_S = 0.3
"""Dwell after switching the gripper (vacuum build-up / release), seconds."""
ACTION_DWELL_S = 1.0
"""Dwell at a task point while the action runs, seconds."""
PTP_SPEED = 0.5
"""Joint speed of PTP moves as a fraction of each axis' maximum."""


@dataclass(frozen=True, eq=False)
class Waypoint:
    """A Cartesian motion target of one element's motion.

    An ``optional`` waypoint (a PTP via point) is left out where the arm cannot
    reach it, instead of failing the program.
    """

    kind: str
    T_world_tool: np.ndarray
    speed: float
    blend: float
    label: str
    element: str
    optional: bool = False


@dataclass(frozen=True)
class Action:
    """Switch an output, then dwell."""

    output: str
    value: bool
    dwell: float
    element: str


Step = Waypoint | Action


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


def element_motion(
    element: Element, project: Project, T_world_pick: np.ndarray, safe_z: float | None = None
) -> list[Step]:
    """The motion steps that build one element.

    Parameters
    ----------
    element
        The element to build.
    project
        Speeds, approach distance and blending come from ``project.program``.
    T_world_pick
        Tool pose gripping a block in the platform magazine, in the world
        (``T_world_base @ T_base_pick_tool(project)`` with the localized base).
    safe_z
        For a block, a tool height (world z, metres) above the structure: the
        block rises straight up to it from the magazine ("lift", linear), is
        carried at it to above its place ("travel", PTP), goes straight down to
        the place approach (linear) and, once placed, the tool rises to it again
        ("depart", linear), so that the only joint-interpolated moves between the
        magazine and the place run above what is built (the re-planning of a
        collision).
    """
    settings = project.program
    approach, blend, speed = settings.approach, settings.blend, settings.speed
    eid = element.id
    if element.type == "block":
        approach = block_approach(element, project)
        T_place = element_tool_frames(element)[0]
        T_pick = T_world_pick
        pick_up, place_up = approach_poses(np.stack([T_pick, T_place]), False, approach)
        steps: list[Step] = [
            Waypoint("ptp", pick_up, PTP_SPEED, blend, "pick approach", eid),
            Waypoint("lin", T_pick, speed, 0.0, "pick", eid),
            Action("gripper", True, GRIP_DWELL_S, eid),
            Waypoint("lin", pick_up, speed, blend, "pick retract", eid),
        ]
        replan = safe_z is not None
        safe = max(pick_up[2, 3], place_up[2, 3], -np.inf if safe_z is None else safe_z)
        if replan and safe > pick_up[2, 3] + 1e-3:
            # straight up from the magazine, across at the safe height, straight down
            lift = pick_up.copy()
            lift[2, 3] = safe
            steps.append(Waypoint("lin", lift, speed, blend, "lift", eid))
        travel_z = safe
        if travel_z > place_up[2, 3] + 1e-3:
            travel = place_up.copy()
            travel[2, 3] = travel_z
            steps.append(
                Waypoint("ptp", travel, PTP_SPEED, blend, "travel", eid, optional=not replan)
            )
        steps += [
            Waypoint("lin" if replan and travel_z > place_up[2, 3] + 1e-3 else "ptp", place_up,
                     speed if replan else PTP_SPEED, blend, "place approach", eid),
            Waypoint("lin", T_place, speed, 0.0, "place", eid),
            Action("gripper", False, GRIP_DWELL_S, eid),
            Waypoint("lin", place_up, speed, blend, "place retract", eid),
        ]  # fmt: skip
        if replan and safe > place_up[2, 3] + 1e-3:
            depart = place_up.copy()
            depart[2, 3] = safe
            steps.append(Waypoint("lin", depart, speed, blend, "depart", eid))
        return steps
    if element.type == "print_path":
        return _print_motion(element, approach, blend, speed)
    T_point = element_tool_frames(element)[0]
    backed = approach_poses(T_point, True, approach)
    action = str(element.attributes.get("action", "mark"))
    return [
        Waypoint("ptp", backed, PTP_SPEED, blend, "approach", eid),
        Waypoint("lin", T_point, speed, 0.0, action, eid),
        Action(action, True, ACTION_DWELL_S, eid),
        Action(action, False, 0.0, eid),
        Waypoint("lin", backed, speed, blend, "retract", eid),
    ]


def _print_motion(element: Element, approach: float, blend: float, speed: float) -> list[Step]:
    """Approach, extrude along the path (travel segments with the extruder off), retract.

    The nozzle is rotationally symmetric, so the tool keeps one rotation about
    its axis for the whole layer (the element frame's x axis) instead of turning
    with the path: a closed contour would otherwise wind the wrist a full turn
    per layer. The path-aligned frames stay available from
    :func:`fabflow.tasks.targets.element_tool_frames`.
    """
    eid = element.id
    frames = element_tool_frames(element).copy()
    frames[:, :3, :3] = np.asarray(element.T_world_element)[:3, :3] @ R_FLIP_X
    n = len(frames)
    extrude = np.asarray(element.attributes.get("extrude", np.ones(max(n - 1, 0))), dtype=bool)
    print_speed = float(element.attributes.get("speed", speed))
    steps: list[Step] = [
        Waypoint(
            "ptp", approach_poses(frames[0], False, approach), PTP_SPEED, blend, "approach", eid
        ),
        Waypoint("lin", frames[0], speed, 0.0, "start", eid),
    ]
    on = False
    for i in range(1, n):
        if extrude[i - 1] != on:
            on = bool(extrude[i - 1])
            steps.append(Action("extruder", on, 0.0, eid))
        last = i == n - 1 or extrude[i] != on
        steps.append(
            Waypoint(
                "lin",
                frames[i],
                print_speed if on else speed,
                0.0 if last else blend,
                "end" if i == n - 1 else f"path {i}",
                eid,
            )
        )
    if on:
        steps.append(Action("extruder", False, 0.0, eid))
    steps.append(
        Waypoint("lin", approach_poses(frames[-1], False, approach), speed, blend, "retract", eid)
    )
    return steps


def work_package_motion(
    elements: Sequence[Element],
    project: Project,
    T_world_base: np.ndarray,
    safe_z: dict[str, float] | None = None,
) -> list[Step]:
    """The motion steps of a whole work package, elements in the given order.

    ``safe_z`` gives the elements re-planned over the structure their safe tool
    height (see :func:`element_motion`).
    """
    T_world_pick = np.asarray(T_world_base, dtype=float) @ T_base_pick_tool(project)
    safe_z = safe_z or {}
    steps: list[Step] = []
    for element in elements:
        steps += element_motion(element, project, T_world_pick, safe_z.get(element.id))
    return steps
