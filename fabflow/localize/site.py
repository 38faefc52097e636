"""What the project puts on the site for localization, in the world frame.

UWB anchors (surveyed in the UWB frame, placed by ``T_world_uwb``), the total
station's set-up pose, and the site obstacles as plain tuples. The build draws
them on the site plan; the localization methods measure against them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fabflow.project import Project, UwbSetup


def points_in_world(T_world_frame: np.ndarray, p_frame: np.ndarray) -> np.ndarray:
    """``(n, 3)`` points of a frame in the world: ``p @ R.T + t`` (metres).

    The UWB geometry is evaluated in this row-vector order (not
    :func:`~fabflow.transforms.se3.apply_T`'s ``R @ p.T``, which rounds the last
    bit differently), so that the seeded simulated ranges stay reproducible.
    """
    return p_frame @ T_world_frame[:3, :3].T + T_world_frame[:3, 3]


def anchors_world(setup: UwbSetup) -> tuple[list[str], np.ndarray]:
    """Anchor ids and their ``(n, 3)`` positions in the world (metres, ``T_world_uwb`` applied)."""
    ids = list(setup.anchors)
    A = np.array([setup.anchors[k] for k in ids], dtype=float)
    return ids, points_in_world(setup.T_world_uwb.matrix(), A)


def site_sensors(project: Project) -> tuple[dict[str, np.ndarray] | None, np.ndarray | None]:
    """UWB anchors by id (world frame, metres) and the total station's 4x4 set-up pose.

    Either is ``None`` when the project has no such section; the set-up pose is
    ``None`` too when it is to be planned (:mod:`fabflow.localize.setups`).
    """
    loc = project.localization
    anchors = None
    if loc.uwb is not None:
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
