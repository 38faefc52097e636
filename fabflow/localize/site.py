"""What the project puts on the site for localization, in the world frame.

UWB anchors (surveyed in the UWB frame, placed by ``T_world_uwb``), the total
station's set-up pose, and the site obstacles as plain tuples. The build draws
them on the site plan; the localization methods measure against them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fabflow.design.elements import Element, element_boxes
from fabflow.project import Project, UwbSetup
from fabflow.tasks.plan import Plan


def points_in_world(T_world_frame: np.ndarray, p_frame: np.ndarray) -> np.ndarray:
    """``(n, 3)`` points of a frame in the world: ``p @ R.T + t`` (metres).

    The UWB geometry is evaluated in this row-vector order (not
    :func:`~fabflow.transforms.se3.apply_T`'s ``R @ p.T``, which rounds the last
    bit differently), so that the seeded simulated ranges stay reproducible.
    """
    return p_frame @ T_world_frame[:3, :3].T + T_world_frame[:3, 3]


def parking_accuracy(project: Project) -> tuple[float, float]:
    """How well the platform parks where it is sent: XY sigma per axis (metres) and
    heading sigma (radians); ``localization.integrity.parking_sigma`` and
    ``parking_sigma_deg``, by default the simulation's driving error."""
    policy = project.localization.integrity
    sim = project.simulation
    s_xy = sim.driving_error if policy.parking_sigma is None else policy.parking_sigma
    s_deg = (
        sim.driving_heading_error_deg
        if policy.parking_sigma_deg is None
        else policy.parking_sigma_deg
    )
    return float(s_xy), float(np.radians(s_deg))


def anchors_world(setup: UwbSetup) -> tuple[list[str], np.ndarray]:
    """Anchor ids and their ``(n, 3)`` positions in the world (metres, ``T_world_uwb`` applied)."""
    ids = list(setup.anchors)
    A = np.array([setup.anchors[k] for k in ids], dtype=float).reshape(-1, 3)
    return ids, points_in_world(setup.T_world_uwb.matrix(), A)


def site_sensors(project: Project) -> tuple[dict[str, np.ndarray] | None, np.ndarray | None]:
    """UWB anchors by id (world frame, metres) and the total station's 4x4 set-up pose.

    Either is ``None`` when the project has no such section; the set-up pose is
    ``None`` too when it is to be planned (:mod:`fabflow.localize.setups`).
    """
    loc = project.localization
    anchors = None
    if loc.uwb is not None and loc.uwb.anchors:
        ids, A = anchors_world(loc.uwb)
        anchors = dict(zip(ids, A, strict=True))
    station = loc.total_station
    given = None if station is None else station.T_world_instrument
    instrument = None if given is None else given.matrix()
    return anchors, instrument


def site_obstacles(project: Project) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """The project's box and polygon obstacles as hashable tuples (metres).

    Returns
    -------
    boxes, prisms
        ``((lower xyz), (upper xyz))`` per box; ``(plan polygon, z_min, z_max)`` per
        polygon obstacle.
    """
    obstacles = project.site.obstacles
    boxes = tuple((tuple(o.box.min), tuple(o.box.max)) for o in obstacles if o.box is not None)
    prisms = tuple(
        (tuple(tuple(p) for p in o.polygon.points), o.polygon.z_min, o.polygon.z_max)
        for o in obstacles
        if o.polygon is not None
    )
    return boxes, prisms


MAX_POSITIONS = 1200
"""Most grid positions a site is searched on for a tripod or an anchor: on a larger
site the grid is coarser than asked (the work stays bounded)."""


def free_ground(
    project: Project,
    elements: Sequence[Element],
    plan: Plan,
    spacing: float,
    clearance: float,
) -> np.ndarray:
    """``(m, 2)`` points of a ``spacing`` grid over the site (world, metres) where a tripod
    or an anchor pole may stand for the whole build (coarser than ``spacing`` where
    the site would hold more than :data:`MAX_POSITIONS` grid points).

    Left out: points within ``clearance`` of an element's plan footprint (its
    bounding rectangle), of an obstacle, or of the platform parked at any station
    (its footprint plus ``safety_margin``). The ground is at z = 0.
    """
    (x0, y0), (x1, y1) = project.site.extent_min, project.site.extent_max
    spacing = max(spacing, float(np.sqrt((x1 - x0) * (y1 - y0) / MAX_POSITIONS)))
    xs = np.arange(x0 + 0.5 * spacing, x1, spacing)
    ys = np.arange(y0 + 0.5 * spacing, y1, spacing)
    xy = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    keep = np.ones(len(xy), dtype=bool)
    T_box, extents = element_boxes(elements)
    if len(extents):
        corner = (np.abs(T_box[:, :2, :3]) @ (0.5 * extents)[..., None])[..., 0]
        lo = T_box[:, :2, 3] - corner - clearance
        hi = T_box[:, :2, 3] + corner + clearance
        for start in range(0, len(xy), 4096):
            p = xy[start : start + 4096, None, :]
            inside = ((p >= lo[None]) & (p <= hi[None])).all(axis=2).any(axis=1)
            keep[start : start + 4096] &= ~inside
    for obstacle in project.site.obstacles:
        if obstacle.box is not None:
            lo2, hi2 = np.asarray(obstacle.box.min[:2]), np.asarray(obstacle.box.max[:2])
        else:
            assert obstacle.polygon is not None
            pts = np.asarray(obstacle.polygon.points, dtype=float)
            lo2, hi2 = pts.min(axis=0), pts.max(axis=0)
        keep &= ~((xy >= lo2 - clearance) & (xy <= hi2 + clearance)).all(axis=1)
    pf = project.robot.platform
    half = 0.5 * np.asarray(pf.footprint, dtype=float) + pf.safety_margin + clearance
    for station in plan.stations:
        T = np.asarray(station.T_world_platform, dtype=float)
        local = (xy - T[:2, 3]) @ T[:2, :2]
        keep &= ~(np.abs(local) <= half).all(axis=1)
    return xy[keep]
