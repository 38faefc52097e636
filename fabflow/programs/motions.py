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
from fabflow.tasks.targets import (
    T_base_home_tool,
    T_base_pick_tool,
    approach_poses,
    block_approach,
    element_tool_frames,
)
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
    reach it, instead of failing the program. A ``seated`` linear move takes a
    held block into its place between its neighbours: its orientation must not
    stray on the way, so where it passes the wrist singularity it becomes a
    joint move (exact orientation, a few millimetres off the line) rather than
    a wrist-interpolated one (on the line, turned by up to 2 deg, which swings
    the ends of a 0.6 m block by 10 mm). A ``free`` linear move draws the empty
    tool in above the structure: where it passes the wrist singularity it may
    become a joint move however far its path bows off the line (the collision
    check follows the bow).
    """

    kind: str
    T_world_tool: np.ndarray
    speed: float
    blend: float
    label: str
    element: str
    optional: bool = False
    seated: bool = False
    free: bool = False


@dataclass(frozen=True)
class Action:
    """Switch an output, then dwell."""

    output: str
    value: bool
    dwell: float
    element: str


Step = Waypoint | Action


@dataclass(frozen=True)
class Route:
    """How a re-planned block travels between the magazine and its place.

    Attributes
    ----------
    height
        Tool height (world z, metres) of the travel: the block rises straight up
        to it from the magazine and comes straight down from it to its place
        approach. None: the higher of the two approach poses.
    tuck
        None: the block is carried across at ``height`` by one joint move.
        A radius about the A1 axis (metres): the arm turns about A1 with the tool
        at that radius only, and the block goes out to its place, and the tool
        back in after the release, by linear moves along the radius. A swing
        between the magazine behind the arm and a far place then sweeps no wider
        than the tucked arm.
    joint_descent
        Down from the travel height to the place approach, and back up after the
        release, by joint moves instead of linear ones: a linear move there can
        take A5 through 0 (which a controller refuses in a linear move), a joint
        move does it with a turn of A4 and A6 (and the collision check follows
        its bow).
    """

    height: float | None = None
    tuck: float | None = None
    joint_descent: bool = False


@dataclass(frozen=True, eq=False)
class Placement:
    """How a block goes into its place where the structure standing around it asks
    for more than the plain descent from :func:`block_approach` above it.

    Attributes
    ----------
    approach
        Distance above the place where the descent starts (metres), when longer
        than :func:`block_approach`: neighbours standing higher than the block's
        own layer.
    slide
        Offset (3,) of where the block is lowered onto its bed from its place
        (world, metres), to slide in along the bed; None: straight down.
    """

    approach: float | None = None
    slide: np.ndarray | None = None


def tucked(T_world_tool: np.ndarray, T_world_base: np.ndarray, radius: float) -> np.ndarray:
    """The tool pose moved along its radius about the A1 axis to ``radius`` (metres).

    The radius is measured in the robot base frame's xy plane; the height in the
    base frame and the orientation stay.
    """
    T_base_tool = np.linalg.solve(T_world_base, T_world_tool)
    xy = T_base_tool[:2, 3]
    r = float(np.hypot(*xy))
    T_base_tool[:2, 3] = xy * (radius / r) if r > 1e-9 else (radius, 0.0)
    return T_world_base @ T_base_tool


def _raised(T: np.ndarray, z: float) -> np.ndarray:
    out = T.copy()
    out[2, 3] = z
    return out


def element_motion(
    element: Element,
    project: Project,
    T_world_pick: np.ndarray,
    route: Route | None = None,
    T_world_base: np.ndarray | None = None,
    placement: Placement | None = None,
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
    route
        For a block re-planned around a collision, how it travels between the
        magazine and its place (:class:`Route`); None: by joint moves through
        its approach poses.
    T_world_base
        The station's localized base pose, for a route with a ``tuck``.
    placement
        For a block, how it goes into its place where the structure around it
        asks for more than the plain descent (:class:`Placement`,
        :func:`fabflow.programs.collision_model.placements`).
    """
    settings = project.program
    approach, blend, speed = settings.approach, settings.blend, settings.speed
    if element.type == "block":
        return _block_motion(element, project, T_world_pick, route, T_world_base, placement)
    if element.type == "print_path":
        return _print_motion(element, approach, blend, speed)
    eid = element.id
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


def _block_motion(
    element: Element,
    project: Project,
    T_pick: np.ndarray,
    route: Route | None,
    T_world_base: np.ndarray | None,
    placement: Placement | None,
) -> list[Step]:
    """Pick in the magazine, carry, place (see the module docstring, :class:`Route` and
    :class:`Placement`)."""
    blend, speed = project.program.blend, project.program.speed
    eid = element.id
    placement = placement or Placement()
    T_place = element_tool_frames(element)[0]
    T_seat = T_place.copy()  # where the block comes down onto its bed
    if placement.slide is not None:
        T_seat[:3, 3] += np.asarray(placement.slide, dtype=float)
    approach = max(block_approach(element, project), placement.approach or 0.0)
    pick_up, seat_up, place_up = approach_poses(
        np.stack([T_pick, T_seat, T_place]), False, approach
    )
    placing = _release(T_seat, T_place, place_up, speed, blend, eid)
    if route is None:
        # through a travel point at the pick height where the arm reaches it
        steps: list[Step] = [Waypoint("ptp", pick_up, PTP_SPEED, blend, "pick approach", eid)]
        steps += _grip(T_pick, pick_up, speed, blend, eid)
        if pick_up[2, 3] > seat_up[2, 3] + 1e-3:
            travel = _raised(seat_up, pick_up[2, 3])
            steps.append(Waypoint("ptp", travel, PTP_SPEED, blend, "travel", eid, optional=True))
        steps.append(Waypoint("ptp", seat_up, PTP_SPEED, blend, "place approach", eid))
        return steps + placing
    tuck = route.tuck
    if tuck is not None and T_world_base is None:
        raise ValueError("a tucked route needs the station's base pose")
    low = max(pick_up[2, 3], seat_up[2, 3])
    height = max(low, route.height if route.height is not None else low)
    steps = []
    if height > pick_up[2, 3] + 1e-3 and tuck is not None:
        # come down onto the magazine from the tucked height
        steps.append(
            Waypoint("ptp", _raised(pick_up, height), PTP_SPEED, blend, "over magazine", eid)
        )
        steps.append(Waypoint("lin", pick_up, speed, blend, "pick approach", eid))
    else:
        steps.append(Waypoint("ptp", pick_up, PTP_SPEED, blend, "pick approach", eid))
    steps += _grip(T_pick, pick_up, speed, blend, eid)
    if height > pick_up[2, 3] + 1e-3:
        steps.append(Waypoint("lin", _raised(pick_up, height), speed, blend, "lift", eid))
    above = _raised(seat_up, height)
    here = above
    if tuck is None:
        label = "travel" if _apart(above, seat_up) else "place approach"
        steps.append(Waypoint("ptp", above, PTP_SPEED, blend, label, eid))
    else:
        here = tucked(above, T_world_base, tuck)
        steps.append(Waypoint("ptp", here, PTP_SPEED, blend, "tuck", eid))
        if _apart(above, seat_up) and _apart(here, above):
            steps.append(Waypoint("lin", above, speed, blend, "travel", eid))
            here = above
    kind, vertical = ("ptp", PTP_SPEED) if route.joint_descent else ("lin", speed)
    if _apart(here, seat_up):
        steps.append(Waypoint(kind, seat_up, vertical, blend, "place approach", eid))
    steps += placing
    depart = _raised(place_up, height)
    if _apart(depart, place_up):
        steps.append(Waypoint(kind, depart, vertical, blend, "depart", eid))
    if tuck is not None:
        T_in = tucked(depart, T_world_base, tuck)
        if _apart(T_in, depart):
            steps.append(Waypoint("lin", T_in, speed, blend, "tuck in", eid, free=True))
    return steps


def _apart(T_a: np.ndarray, T_b: np.ndarray) -> bool:
    """Whether two tool poses are more than a millimetre apart."""
    return bool(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]) > 1e-3)


def _grip(
    T_pick: np.ndarray, pick_up: np.ndarray, speed: float, blend: float, eid: str
) -> list[Step]:
    return [
        Waypoint("lin", T_pick, speed, 0.0, "pick", eid),
        Action("gripper", True, GRIP_DWELL_S, eid),
        Waypoint("lin", pick_up, speed, blend, "pick retract", eid),
    ]


def _release(
    T_seat: np.ndarray,
    T_place: np.ndarray,
    place_up: np.ndarray,
    speed: float,
    blend: float,
    eid: str,
) -> list[Step]:
    """Down onto the bed at ``T_seat`` (slid in along the bed where that is not the
    place), release, retract straight up."""
    seat: list[Step] = []
    if _apart(T_seat, T_place):
        seat.append(Waypoint("lin", T_seat, speed, 0.0, "seat", eid, seated=True))
    return [
        *seat,
        Waypoint("lin", T_place, speed, 0.0, "place", eid, seated=True),
        Action("gripper", False, GRIP_DWELL_S, eid),
        Waypoint("lin", place_up, speed, blend, "place retract", eid, seated=True),
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
    routes: dict[str, Route] | None = None,
    placements: dict[str, Placement] | None = None,
) -> list[Step]:
    """The motion steps of a whole work package, elements in the given order.

    ``routes`` gives the blocks re-planned around a collision their route and
    ``placements`` the blocks the structure around their place asks more of
    their placement (see :func:`element_motion`). A tucked block starts by
    drawing the tool in from where the block before it ended ("tuck in", a move
    of the tucked block) to its tuck radius, so that the joint move back to the
    magazine turns the arm tucked too. A package whose last block is tucked ends
    "over home": HOME's tool position at the tucked height, from where the
    program's HOME move folds the arm over the platform.
    """
    T_world_base = np.asarray(T_world_base, dtype=float)
    T_world_pick = T_world_base @ T_base_pick_tool(project)
    routes, placements = routes or {}, placements or {}
    speed, blend = project.program.speed, project.program.blend
    steps: list[Step] = []
    for k, element in enumerate(elements):
        route = routes.get(element.id)
        steps += element_motion(
            element, project, T_world_pick, route, T_world_base, placements.get(element.id)
        )
        following = routes.get(elements[k + 1].id) if k + 1 < len(elements) else None
        last = steps[-1]
        if (
            element.type == "block"
            and (route is None or route.tuck is None)
            and following is not None
            and following.tuck is not None
            and isinstance(last, Waypoint)
        ):
            # the next block's move: its route owns it (and is re-planned if it fails)
            T_in = tucked(last.T_world_tool, T_world_base, following.tuck)
            if _apart(T_in, last.T_world_tool):
                tuck_in = Waypoint(
                    "lin", T_in, speed, blend, "tuck in", elements[k + 1].id, free=True
                )
                steps.append(tuck_in)
    if elements and steps and isinstance(steps[-1], Waypoint):
        route = routes.get(elements[-1].id)
        if elements[-1].type == "block" and route is not None and route.tuck is not None:
            # turn to HOME at the tucked height, then fold into it over the platform:
            # the joint move HOME alone would lower the arm while it turns
            T_over = T_world_base @ T_base_home_tool(project)
            T_over[2, 3] = max(T_over[2, 3], steps[-1].T_world_tool[2, 3])
            steps.append(Waypoint("ptp", T_over, PTP_SPEED, blend, "over home", elements[-1].id))
    return steps
