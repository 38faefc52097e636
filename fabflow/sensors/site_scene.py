"""A simulated building site as one triangle mesh, for LiDAR ray casting.

The scene (world frame, metres, z up, ground at z = 0) holds what paper 000's
site map shows: flat ground, a site barrack with a pitched roof, a bridge deck on
round columns, and a site container; compact objects lying around (pallets,
barrels, a generator, a cable drum: the segments global registration matches);
plus the project's box and polygon obstacles and the blocks of the structure
built so far (any :class:`~fabflow.design.elements.Element`
with ``extents``). The landmarks sit around the default cabin footprint
(x 0..4 m, y 0..3.3 m), within 20 m LiDAR range of every station.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

from fabflow.design.elements import Element, element_boxes
from fabflow.transforms.se3 import make_T
from fabflow.transforms.so3 import exp_so3

FloatArray = NDArray[np.float64]

_UNIT_BOX = trimesh.creation.box(extents=(1.0, 1.0, 1.0))


@dataclass(frozen=True)
class SiteLandmarks:
    """Placement of the static landmarks of the simulated site (world frame, metres).

    Attributes
    ----------
    offset
        Shift of all landmarks in the ground plane (x, y), e.g. to centre them on
        another footprint.
    ground_half_size
        The ground is a square of twice this edge, centred on ``offset``.
    """

    offset: tuple[float, float] = (0.0, 0.0)
    ground_half_size: float = 30.0


def box_mesh(lower: Sequence[float], upper: Sequence[float]) -> trimesh.Trimesh:
    """An axis-aligned box between two corners (metres)."""
    return trimesh.creation.box(bounds=np.array([lower, upper], dtype=float))


def boxes_mesh(T_world_box: NDArray[np.float64], extents: NDArray[np.float64]) -> trimesh.Trimesh:
    """Many oriented boxes as one mesh, built without a Python loop over boxes.

    Parameters
    ----------
    T_world_box
        ``(n, 4, 4)`` box centre poses (metres).
    extents
        ``(n, 3)`` box edge lengths along the box axes (metres).
    """
    T = np.asarray(T_world_box, dtype=float).reshape(-1, 4, 4)
    ext = np.asarray(extents, dtype=float).reshape(-1, 3)
    n = len(T)
    if n == 0:
        return trimesh.Trimesh()
    corners = _UNIT_BOX.vertices[None, :, :] * ext[:, None, :]
    verts = np.einsum("nij,nkj->nki", T[:, :3, :3], corners) + T[:, None, :3, 3]
    faces = _UNIT_BOX.faces[None, :, :] + (np.arange(n) * len(_UNIT_BOX.vertices))[:, None, None]
    return trimesh.Trimesh(verts.reshape(-1, 3), faces.reshape(-1, 3), process=False)


def prism_mesh(points: Sequence[Sequence[float]], z_min: float, z_max: float) -> trimesh.Trimesh:
    """A vertical prism: a plan polygon (metres, any simple polygon) from ``z_min`` to ``z_max``.

    Caps are the Delaunay triangles of the polygon's vertices that lie inside it
    (shapely), walls one quad per edge.
    """
    from shapely.geometry import Polygon
    from shapely.ops import triangulate

    xy = np.asarray(points, dtype=float).reshape(-1, 2)
    poly = Polygon(xy)
    tris = [t for t in triangulate(poly) if poly.contains(t.representative_point())]
    cap = np.array([np.asarray(t.exterior.coords)[:3] for t in tris]).reshape(-1, 2)
    n_cap = len(cap)
    cap_v = np.vstack([np.c_[cap, np.full(n_cap, z_min)], np.c_[cap, np.full(n_cap, z_max)]])
    idx = np.arange(n_cap).reshape(-1, 3)
    cap_f = np.vstack([idx[:, ::-1], idx + n_cap])
    a, b = xy, np.roll(xy, -1, axis=0)
    m = len(xy)
    wall_v = np.vstack(
        [np.c_[a, np.full(m, z_min)], np.c_[b, np.full(m, z_min)],
         np.c_[b, np.full(m, z_max)], np.c_[a, np.full(m, z_max)]]
    )  # fmt: skip
    k = np.arange(m)
    quads = np.stack([k, k + m, k + 2 * m, k + 3 * m], axis=1) + len(cap_v)
    wall_f = np.vstack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return trimesh.Trimesh(np.vstack([cap_v, wall_v]), np.vstack([cap_f, wall_f]), process=False)


def _barrack(x0: float, y0: float) -> list[trimesh.Trimesh]:
    body = box_mesh((x0, y0, 0.0), (x0 + 6.0, y0 + 2.5, 2.6))
    # gable roof ridge along x: a triangular prism
    verts = np.array(
        [
            [x0 - 0.2, y0 - 0.2, 2.6],
            [x0 - 0.2, y0 + 2.7, 2.6],
            [x0 - 0.2, y0 + 1.25, 3.4],
            [x0 + 6.2, y0 - 0.2, 2.6],
            [x0 + 6.2, y0 + 2.7, 2.6],
            [x0 + 6.2, y0 + 1.25, 3.4],
        ]
    )
    faces = np.array(
        [[0, 2, 1], [3, 4, 5], [0, 3, 5], [0, 5, 2], [1, 2, 5], [1, 5, 4], [0, 1, 4], [0, 4, 3]]
    )
    roof = trimesh.Trimesh(verts, faces, process=False)
    step = box_mesh((x0 + 2.5, y0 - 0.6, 0.0), (x0 + 3.5, y0, 0.3))
    return [body, roof, step]


def _bridge(x0: float, y0: float) -> list[trimesh.Trimesh]:
    parts = [box_mesh((x0, y0, 4.0), (x0 + 14.0, y0 + 3.0, 4.7))]
    parts.append(box_mesh((x0, y0 - 0.1, 4.7), (x0 + 14.0, y0 + 0.1, 5.6)))  # railing wall
    for cx in (x0 + 1.5, x0 + 6.0, x0 + 10.5):
        for cy in (y0 + 0.7, y0 + 2.3):
            col = trimesh.creation.cylinder(radius=0.3, height=4.0, sections=20)
            col.apply_translation((cx, cy, 2.0))
            parts.append(col)
    return parts


def _site_objects(ox: float, oy: float) -> list[trimesh.Trimesh]:
    """Compact objects lying around: timber pallets, barrels, a generator, a cable drum."""
    parts = []
    for x, y, yaw, ext in (
        (-3.5, -2.0, 0.3, (1.2, 0.8, 0.8)),
        (7.5, -1.5, -0.5, (1.2, 0.8, 1.1)),
        (-4.0, 3.5, 1.1, (1.0, 0.7, 0.8)),
        (5.0, 7.5, 0.0, (2.4, 1.2, 0.5)),
    ):
        T = make_T(exp_so3(np.array([0.0, 0.0, yaw])), [ox + x, oy + y, ext[2] / 2])
        parts.append(trimesh.creation.box(extents=ext, transform=T))
    for x, y in ((8.0, 1.0), (8.7, 1.3), (-2.5, -4.5)):
        barrel = trimesh.creation.cylinder(radius=0.3, height=0.9, sections=16)
        barrel.apply_translation((ox + x, oy + y, 0.45))
        parts.append(barrel)
    drum = trimesh.creation.cylinder(
        radius=0.6,
        height=0.5,
        sections=20,
        transform=make_T(exp_so3(np.array([np.pi / 2, 0.0, 0.0])), [ox - 1.0, oy + 6.5, 0.6]),
    )
    parts.append(drum)
    return parts


def site_scene(
    built: Sequence[Element] = (),
    obstacles: Sequence[tuple[Sequence[float], Sequence[float]]] = (),
    landmarks: SiteLandmarks | None = SiteLandmarks(),
    prisms: Sequence[tuple[Sequence[Sequence[float]], float, float]] = (),
) -> trimesh.Trimesh:
    """The simulated site as one mesh in the world frame.

    Parameters
    ----------
    built
        Elements already built (blocks with ``extents``; others are ignored), placed
        at their ``T_world_element``.
    obstacles
        Extra axis-aligned boxes ``(lower, upper)`` (metres), e.g. the project's
        site obstacles.
    landmarks
        Where the ground, barrack, bridge and container go; ``None`` for a scene
        of only ``built`` and ``obstacles``.
    prisms
        Extra vertical prisms ``(plan polygon, z_min, z_max)`` (metres), e.g. the
        project's polygon obstacles.

    Returns
    -------
    trimesh.Trimesh
        All geometry merged (not watertight; ray casting only needs triangles).
    """
    parts: list[trimesh.Trimesh] = []
    if landmarks is not None:
        ox, oy = landmarks.offset
        h = landmarks.ground_half_size
        ground = trimesh.Trimesh(
            np.array(
                [
                    [ox - h, oy - h, 0.0],
                    [ox + h, oy - h, 0.0],
                    [ox + h, oy + h, 0.0],
                    [ox - h, oy + h, 0.0],
                ]
            ),
            np.array([[0, 1, 2], [0, 2, 3]]),
            process=False,
        )
        parts.append(ground)
        parts += _barrack(ox - 9.0, oy + 6.0)
        parts += _bridge(ox - 4.0, oy - 9.0)
        container = trimesh.creation.box(
            extents=(6.06, 2.44, 2.59),
            transform=make_T(
                exp_so3(np.array([0.0, 0.0, np.radians(25.0)])), [ox + 11.0, oy + 5.0, 1.295]
            ),
        )
        parts.append(container)
        parts += _site_objects(ox, oy)
    for lower, upper in obstacles:
        parts.append(box_mesh(lower, upper))
    for polygon, z_min, z_max in prisms:
        parts.append(prism_mesh(polygon, z_min, z_max))
    T_boxes, extents = element_boxes(built)
    if len(extents):
        parts.append(boxes_mesh(T_boxes, extents))
    if not parts:
        return trimesh.Trimesh()
    return trimesh.util.concatenate(parts)
