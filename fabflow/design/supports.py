"""Geometric relations between boxes: which block rests on which, and overlaps.

Boxes are given by their poses ``T_world_box`` (centre of the box, metres) and
their ``extents`` (size along the box's own x, y, z). The plan footprint of a box
is the convex hull of its eight corners projected on the world xy plane, its
vertical range the span of the corners' z. Candidate pairs come from an STR-tree
of the footprints' bounding boxes, are filtered by their z ranges with numpy and
only then intersected exactly (shapely, vectorized): no Python loop over pairs.
"""

from __future__ import annotations

import numpy as np
import shapely

from fabflow.transforms import apply_T

_CORNERS = np.array(
    [[sx, sy, sz] for sx in (-0.5, 0.5) for sy in (-0.5, 0.5) for sz in (-0.5, 0.5)]
)


def box_corners(T_world_box: np.ndarray, extents: np.ndarray) -> np.ndarray:
    """The eight corners of every box in the world frame.

    Parameters
    ----------
    T_world_box
        (N, 4, 4) box poses (centre, metres).
    extents
        (N, 3) box sizes along the box axes (metres).

    Returns
    -------
    numpy.ndarray
        (N, 8, 3) corners in the world frame (metres).
    """
    local = _CORNERS[None, :, :] * np.asarray(extents, dtype=float)[:, None, :]
    return apply_T(np.asarray(T_world_box, dtype=float)[:, None], local)


def box_footprints(corners: np.ndarray) -> np.ndarray:
    """Plan footprints (shapely polygons) of boxes given by their (N, 8, 3) corners."""
    n = corners.shape[0]
    flat = corners[:, :, :2].reshape(-1, 2)
    points = shapely.multipoints(flat, indices=np.repeat(np.arange(n), 8))
    return shapely.convex_hull(points)


def _pairs(footprints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs of different footprints whose bounding boxes overlap."""
    tree = shapely.STRtree(footprints)
    i, j = tree.query(footprints)
    keep = i != j
    return i[keep], j[keep]


def compute_supports(
    T_world_box: np.ndarray,
    extents: np.ndarray,
    contact_tol: float = 1e-6,
    min_area: float = 1e-6,
) -> list[np.ndarray]:
    """For every box, the indices of the boxes it rests on.

    Box ``i`` rests on box ``j`` when the top of ``j`` lies within
    ``contact_tol`` of the bottom of ``i`` and their footprints share more than
    ``min_area`` (so boxes touching only along an edge do not count).

    Parameters
    ----------
    T_world_box
        (N, 4, 4) box poses in the world frame (metres).
    extents
        (N, 3) box sizes (metres).
    contact_tol
        Allowed vertical gap or overlap between the touching faces (metres).
    min_area
        Smallest shared footprint area that counts as contact (square metres).

    Returns
    -------
    list of numpy.ndarray
        ``supports[i]``: sorted indices of the boxes box ``i`` rests on.
    """
    n = len(T_world_box)
    if n == 0:
        return []
    corners = box_corners(T_world_box, extents)
    bottom = corners[:, :, 2].min(axis=1)
    top = corners[:, :, 2].max(axis=1)
    fp = box_footprints(corners)
    i, j = _pairs(fp)
    touching = np.abs(top[j] - bottom[i]) <= contact_tol
    i, j = i[touching], j[touching]
    area = shapely.area(shapely.intersection(fp[i], fp[j]))
    i, j = i[area > min_area], j[area > min_area]
    order = np.lexsort((j, i))
    i, j = i[order], j[order]
    return np.split(j, np.searchsorted(i, np.arange(1, n)))


def max_overlap_volume(T_world_box: np.ndarray, extents: np.ndarray) -> float:
    """The largest volume (cubic metres) any two boxes share.

    Exact for boxes whose axes are vertical (rotated about z only); for tilted
    boxes it bounds the shared volume from above (footprint hulls times z range).
    """
    if len(T_world_box) < 2:
        return 0.0
    corners = box_corners(T_world_box, extents)
    bottom = corners[:, :, 2].min(axis=1)
    top = corners[:, :, 2].max(axis=1)
    fp = box_footprints(corners)
    i, j = _pairs(fp)
    dz = np.minimum(top[i], top[j]) - np.maximum(bottom[i], bottom[j])
    keep = dz > 0
    if not keep.any():
        return 0.0
    i, j, dz = i[keep], j[keep], dz[keep]
    area = shapely.area(shapely.intersection(fp[i], fp[j]))
    return float((area * dz).max())
