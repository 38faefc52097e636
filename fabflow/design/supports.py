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

from fabflow.transforms.se3 import apply_T

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
    T_world_box = np.asarray(T_world_box, dtype=float)
    corners = box_corners(T_world_box, extents)
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    bottom, top = lo[:, 2], hi[:, 2]
    # Contact levels: cluster all face heights (gaps > contact_tol split clusters).
    # Shifting every bounding box sideways by its level number puts boxes at
    # different levels far apart in plan, so the 2D tree only pairs boxes that can touch.
    z = np.concatenate([bottom, top])
    order = np.argsort(z)
    level = np.empty(2 * n, dtype=int)
    level[order] = np.concatenate(([0], np.cumsum(np.diff(z[order]) > contact_tol)))
    pitch = float(hi[:, 0].max() - lo[:, 0].min()) + 1.0
    up_dx, low_dx = level[:n] * pitch, level[n:] * pitch
    upper = shapely.box(lo[:, 0] + up_dx, lo[:, 1], hi[:, 0] + up_dx, hi[:, 1])
    lower = shapely.box(lo[:, 0] + low_dx, lo[:, 1], hi[:, 0] + low_dx, hi[:, 1])
    j, i = shapely.STRtree(lower).query(upper)[::-1]
    keep = (i != j) & (level[i] == level[n + j])
    i, j = i[keep], j[keep]
    # Upright boxes turned by a multiple of 90 degrees are their own bounding boxes:
    # their shared area is plain interval arithmetic. Others go through shapely.
    R = T_world_box[:, :3, :3]
    aligned = (np.abs(R[:, 2, 2] - 1.0) < 1e-9) & (np.abs(R[:, 0, 0] * R[:, 0, 1]) < 1e-12)
    both = aligned[i] & aligned[j]
    overlap = np.clip(np.minimum(hi[i, :2], hi[j, :2]) - np.maximum(lo[i, :2], lo[j, :2]), 0, None)
    area = overlap[:, 0] * overlap[:, 1]
    if not both.all():
        k = np.flatnonzero(~both)
        fp = box_footprints(corners)
        area[k] = shapely.area(shapely.intersection(fp[i[k]], fp[j[k]]))
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
