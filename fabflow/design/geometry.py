"""Triangle meshes of elements (for previews, collision checks and export).

Blocks become boxes of their ``extents`` at their pose; print path layers become
thin ribbons ``bead_width`` wide and ``layer_height`` high along their extruding
segments. Meshes are in the world frame, metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from fabflow.design.elements import Element
from fabflow.design.supports import box_corners

if TYPE_CHECKING:
    import trimesh

# faces of a box whose corners are ordered as in fabflow.design.supports._CORNERS
# (index = 4 * ix + 2 * iy + iz), outward-facing, counter-clockwise
_BOX_FACES = np.array(
    [
        [0, 2, 6], [0, 6, 4],  # bottom (z-)
        [1, 5, 7], [1, 7, 3],  # top (z+)
        [0, 4, 5], [0, 5, 1],  # y-
        [2, 3, 7], [2, 7, 6],  # y+
        [0, 1, 3], [0, 3, 2],  # x-
        [4, 6, 7], [4, 7, 5],  # x+
    ]
)  # fmt: skip


def blocks_mesh(elements: Sequence[Element]) -> trimesh.Trimesh:
    """One mesh holding a box per block (other element types are skipped).

    Face ``12 * k ... 12 * k + 11`` belongs to the ``k``-th block of ``elements``.
    """
    import trimesh

    blocks = [e for e in elements if e.type == "block" and e.extents is not None]
    if not blocks:
        return trimesh.Trimesh()
    T = np.stack([e.T_world_element for e in blocks])
    ext = np.stack([np.asarray(e.extents, dtype=float) for e in blocks])
    vertices = box_corners(T, ext).reshape(-1, 3)
    faces = (_BOX_FACES[None, :, :] + 8 * np.arange(len(blocks))[:, None, None]).reshape(-1, 3)
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def element_mesh(element: Element) -> trimesh.Trimesh:
    """The mesh of one element: a box for a block, a ribbon for a print path layer.

    Task points have no body: the result is an empty mesh.
    """
    import trimesh

    if element.type == "block":
        return blocks_mesh([element])
    if element.type != "print_path" or element.polyline is None:
        return trimesh.Trimesh()
    width = float(element.attributes.get("bead_width", 0.03))
    height = float(element.attributes.get("layer_height", 0.02))
    p = np.asarray(element.polyline, dtype=float)
    extrude = np.asarray(element.attributes.get("extrude", np.ones(len(p) - 1)), dtype=bool)
    a, b = p[:-1][extrude], p[1:][extrude]
    d = b - a
    length = np.linalg.norm(d, axis=1)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, 0, 0], T[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
    T[:, 1, 0], T[:, 1, 1] = np.sin(yaw), np.cos(yaw)
    # the bead sits below the nozzle: centre half a layer below the path
    T[:, :3, 3] = 0.5 * (a + b) - [0.0, 0.0, 0.5 * height]
    ext = np.column_stack([length, np.full(len(a), width), np.full(len(a), height)])
    vertices = box_corners(element.T_world_element @ T, ext).reshape(-1, 3)
    faces = (_BOX_FACES[None, :, :] + 8 * np.arange(len(a))[:, None, None]).reshape(-1, 3)
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
