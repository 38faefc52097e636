"""Where the robot holds the prism at a station, in its base frame (paper 001, eqs 9-11).

The ``arbitrary`` procedure spreads ``n_points`` over the robot's workspace
(:func:`fabflow.positioning.point_selection.optimal_points`) and moves those
that are blocked by the structure, by the arm's own path or, when the
instrument's position is known, by the line of sight
(:func:`~fabflow.positioning.point_selection.avoid_obstacles`). The
``three_point`` procedure holds ``P1, P1 + d x, P1 + d y``; ``P1`` is moved as
a whole to the nearest place where all three are clear, and, when the instrument
does not see them there, to the first of :data:`THREE_POINT_ALTERNATIVES` other
clear places (spread over the workspace) that it sees. The set-up planner
(:mod:`fabflow.localize.setups`) and the localization
(:mod:`fabflow.localize.total_station`) both choose the points here, so the
points a set-up is planned for are the points the robot then shows it.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from fabflow.design.elements import Element, element_boxes
from fabflow.errors import LocalizationError
from fabflow.positioning.boxes import Boxes
from fabflow.positioning.point_selection import (
    ClearanceRules,
    Workspace,
    avoid_obstacles,
    clear_mask,
    clear_workspace_points,
    farthest_points,
    optimal_points,
    reachable_workspace_grid,
)
from fabflow.positioning.polar import Instrument, make_instrument
from fabflow.positioning.three_point import three_point_base_points
from fabflow.project import Project, TotalStationSetup
from fabflow.robots.prism import PrismReach, prism_reach
from fabflow.transforms.se3 import apply_T, inv_T

THREE_POINT_SEARCH_SPACING = 0.1
"""Grid spacing (metres) of the search for a clear ``P1`` of the three-point procedure."""
THREE_POINT_ALTERNATIVES = 12
"""Other clear places of the three points tried, in a fixed order, when a line of sight
blocks the first: the set-up planner plans for the same list."""


def prism_workspace(
    model: str, T_flange_tool: np.ndarray, z_min: float, front: tuple[float, float] = (1.0, 0.0)
) -> tuple[PrismReach, Workspace]:
    """The robot's prism reach and the workspace the prism points are chosen in.

    The workspace is the reach sphere about the shoulder, above ``z_min`` (base
    frame, metres) and in front of the robot (``front``, see
    :func:`platform_front`), with the robot's exact reach test; its top is
    capped at the highest reachable point in front of the robot (5 cm margin),
    because the top of the sphere is out of reach with the tool held down.
    """
    reach = prism_reach(model, T_flange_tool)
    robot = reach.robot
    shoulder = robot.frames(np.zeros(robot.dof))[1][:3, 3]
    ws = Workspace(
        center=(0.0, 0.0, float(shoulder[2])),
        reach=float(robot.reach),
        z_min=z_min,
        front=front,
    )
    x = np.arange(0.1, ws.radius, 0.05)
    z = np.arange(z_min, ws.center[2] + ws.radius, 0.05)
    grid = np.stack(np.meshgrid(x, [0.0], z, indexing="ij"), axis=-1).reshape(-1, 3)
    grid[:, :2] = grid[:, :1] * np.asarray(front)  # along the front, not the base's x
    ok = reach.reachable(grid)
    if not ok.any():
        raise LocalizationError(f"{model}: no prism position above z = {z_min} m is reachable")
    z_max = float(grid[ok, 2].max()) - 0.05
    return reach, replace(ws, reachable=reach.reachable, z_max=z_max)


def platform_front(project: Project) -> tuple[float, float]:
    """The platform's front (its +x) as a unit vector in the robot's base frame: where
    the prism points go (paper 001 puts them in front of the robot, ``x > 0``; an arm
    mounted turned on its platform has its own +x towards the platform's back)."""
    R = project.robot.platform.T_platform_base.matrix()[:3, :3]
    ahead = R.T[:2, 0]
    norm = float(np.linalg.norm(ahead))
    if norm < 1e-9:  # the arm mounted on its side: its own +x
        return (1.0, 0.0)
    return (float(ahead[0] / norm), float(ahead[1] / norm))


@functools.lru_cache(maxsize=16)
def _robot_workspace(
    model: str, tool: bytes, z_min: float, front: tuple[float, float]
) -> tuple[PrismReach, Workspace, np.ndarray]:
    """:func:`prism_workspace` and its reachable pool grid, once per robot, tool,
    ``z_min`` and front (``tool``: the 4x4 TCP's bytes)."""
    reach, ws = prism_workspace(model, np.frombuffer(tool).reshape(4, 4), z_min, front)
    return reach, ws, reachable_workspace_grid(ws)


def boxes_near_base(boxes_world: Boxes, T_world_base: np.ndarray, radius: float) -> Boxes:
    """The world boxes whose bounding spheres come within ``radius`` of the base, in the
    base frame (the rest cannot touch a prism, the arm or a sight line's last metres)."""
    if len(boxes_world) == 0:
        return Boxes.empty()
    T = np.asarray(T_world_base, dtype=float)
    centre = boxes_world.T_base_box[:, :3, 3]
    size = 0.5 * np.linalg.norm(boxes_world.extents, axis=1)
    near = np.linalg.norm(centre - T[:3, 3], axis=1) <= radius + size
    return Boxes(inv_T(T) @ boxes_world.T_base_box[near], boxes_world.extents[near])


@functools.lru_cache(maxsize=64)
def _cached_optimal_points(n: int, workspace: Workspace) -> np.ndarray:
    # a fixed seed: the same workspace always gets the same points
    return optimal_points(n, replace(workspace, reachable=None), np.random.default_rng(0))


def instrument_for(setup: TotalStationSetup) -> Instrument:
    """The accuracy model of a project's total station setup."""
    return make_instrument(
        setup.instrument,
        setup.distance_sigma_mm,
        setup.distance_ppm,
        setup.angle_sigma_arcsec,
        setup.prism_centring_mm,
        setup.atmosphere_ppm,
    )


def total_station_setup(project: Project) -> TotalStationSetup:
    """The project's total station section, or the defaults."""
    return project.localization.total_station or TotalStationSetup()


@dataclass(frozen=True)
class StationPoints:
    """The prism points of one station.

    Attributes
    ----------
    reach
        The robot's prism reach (inverse kinematics of the prism positions).
    points
        ``(n, 3)`` desired prism positions in the base frame (metres).
    moved
        How far each was moved clear of obstacles (metres).
    dropped
        Desired points with no clear replacement, with the reason.
    spare
        ``(k, 3)`` other clear points, most spread first (base frame): where
        blocked points may go when a line of sight is tested later.
    alternatives
        ``three_point``: ``(k, 3, 3)`` other clear places of the three points, most
        spread first (base frame), that a line of sight tested later may choose.
    """

    reach: PrismReach
    points: np.ndarray
    moved: np.ndarray
    dropped: tuple[tuple[int, str], ...]
    spare: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    alternatives: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))


def station_points(
    project: Project,
    T_world_base: np.ndarray,
    built: Sequence[Element] = (),
    sight_from: np.ndarray | None = None,
    station_id: str | None = None,
    spare: int = 0,
    boxes_world: Boxes | None = None,
) -> StationPoints:
    """The prism points the robot shows at a station (see the module docstring).

    Parameters
    ----------
    project
        The project (``localization.total_station``, the robot and its tool).
    T_world_base
        4x4 pose of the robot base (world, metres).
    built
        The structure standing (obstacles for the prism, the arm and the sight).
    sight_from
        ``(3,)`` instrument trunnion in the world: the lines of sight must be
        clear too. ``None``: not tested (the set-up planner tests them itself).
    station_id
        For messages.
    spare
        How many spare clear points to return besides (``StationPoints.spare``; for
        ``three_point``, places of the three points, ``StationPoints.alternatives``).
    boxes_world
        ``built`` as world boxes when already computed (a planner's whole build).

    Raises
    ------
    LocalizationError
        When fewer than three clear points are found (naming the criterion that
        blocked them), or no clear place for the three points of ``three_point``.
    """
    setup = total_station_setup(project)
    T_world_base = np.asarray(T_world_base, dtype=float)
    T_flange_tool = np.ascontiguousarray(project.robot.tool.T_flange_tool.matrix(), dtype=float)
    reach, ws, pool_grid = _robot_workspace(
        project.robot.name, T_flange_tool.tobytes(), float(setup.z_min), platform_front(project)
    )
    if boxes_world is None:
        T_box, extents = element_boxes(built)
        boxes_world = Boxes(T_box, extents) if len(extents) else Boxes.empty()
    # a blocked sight line is tested against every box; the rest only near the robot
    radius = np.inf if sight_from is not None else float(np.linalg.norm(ws.center)) + ws.reach
    boxes = boxes_near_base(boxes_world, T_world_base, radius)
    sight = None
    if sight_from is not None:
        local = apply_T(inv_T(T_world_base), np.asarray(sight_from, dtype=float))
        sight = tuple(float(v) for v in local)
    rules = ClearanceRules(tool_half_extents=setup.tool_half_extents, sight_from=sight)
    if setup.procedure == "three_point":
        d = setup.three_point_step
        blind = replace(rules, sight_from=None)
        points = _three_point_points(ws, boxes, blind, d, station_id)
        # the alternatives only when asked for or when the sight blocks the first place
        # (a prefix of a longer list is the shorter list: the order is fixed)
        blocked = sight is not None and not clear_mask(points, ws, boxes, rules).all()
        k = max(spare, THREE_POINT_ALTERNATIVES) if blocked else spare
        alternatives = (
            _three_point_alternatives(ws, boxes, blind, d, pool_grid, k)
            if k
            else np.zeros((0, 3, 3))
        )
        if blocked:
            # the places a set-up was planned for, in order, before any other in sight
            seen = clear_mask(alternatives.reshape(-1, 3), ws, boxes, rules)
            whole = seen.reshape(-1, 3).all(axis=1)
            if whole.any():
                points = alternatives[int(np.argmax(whole))]
            else:
                points = _three_point_points(ws, boxes, rules, d, station_id)
        return StationPoints(reach, points, np.zeros(3), (), alternatives=alternatives[:spare])
    clear = avoid_obstacles(
        _cached_optimal_points(setup.n_points, ws), ws, boxes, rules, min_points=3
    )
    pool = np.zeros((0, 3))
    if spare:
        pool = farthest_points(
            clear_workspace_points(ws, boxes, rules, reachable_grid=pool_grid), spare
        )
    return StationPoints(reach, clear.points, clear.moved, clear.dropped, pool)


def _three_point_alternatives(
    ws: Workspace, boxes: Boxes, rules: ClearanceRules, d: float, pool_grid: np.ndarray, k: int
) -> np.ndarray:
    """``(<= k, 3, 3)`` places of ``P1, P1 + d x, P1 + d y`` with all three clear, their
    ``P1`` spread over the workspace's clear pool (farthest first)."""
    clear = clear_workspace_points(ws, boxes, rules, reachable_grid=pool_grid)
    sets = three_point_base_points(clear[:, None, :], d)
    ok = clear_mask(sets[:, 1:].reshape(-1, 3), ws, boxes, rules).reshape(-1, 2).all(axis=1)
    return three_point_base_points(farthest_points(sets[ok, 0], k)[:, None, :], d)


def _three_point_points(
    ws: Workspace, boxes: Boxes, rules: ClearanceRules, d: float, station_id: str | None
) -> np.ndarray:
    """``P1, P1 + d x, P1 + d y`` with ``P1`` at its default place, or at the nearest
    place on a grid of :data:`THREE_POINT_SEARCH_SPACING` where all three are clear."""
    c = np.asarray(ws.center)
    ahead = np.r_[ws.front, 0.0]
    p1 = c + 0.55 * ws.radius * ahead - np.array([0.5 * d, 0.5 * d, 0.0])
    P = three_point_base_points(p1, d)
    if clear_mask(P, ws, boxes, rules).all():
        return P
    r = ws.radius
    axes = [np.arange(c[k] - r, c[k] + r + 1e-9, THREE_POINT_SEARCH_SPACING) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    sets = three_point_base_points(grid[:, None, :], d)
    inside = ws.contains_geometry(sets).all(axis=1)
    sets = sets[inside]
    sets = sets[np.argsort(np.linalg.norm(sets[:, 0] - p1, axis=1), kind="stable")]
    # the nearest sets first, in chunks: the reach test solves inverse kinematics
    for start in range(0, len(sets), 256):
        chunk = sets[start : start + 256]
        ok = clear_mask(chunk.reshape(-1, 3), ws, boxes, rules).reshape(-1, 3).all(axis=1)
        if ok.any():
            return chunk[int(np.argmax(ok))]
    raise LocalizationError(
        f"station {station_id}: no place where the three-point localization points P1, "
        f"P1 + {d:g} m x and P1 + {d:g} m y are all clear of the structure and in reach "
        "(and in sight of the instrument); use localization.total_station.procedure "
        "'arbitrary' or a smaller three_point_step"
    )
