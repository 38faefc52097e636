"""An element frame for a box or a shape drawn without one.

A box drawn in Rhino or meshed elsewhere carries no element frame, only its
corners. fabflow's block frame (:mod:`fabflow.design.elements`) sits at the
centre of the box, x along its length, z up; this module picks that frame from
the geometry, the same one for every way the box may be drawn:

* z is the box axis nearest the world's vertical, pointing up;
* x is the longer of the other two, pointing along +x of the world (along +y
  when it is horizontal across x);
* y completes a right-handed frame.

A block is symmetric, so any of the box's frames builds the same block; this
choice makes two files of the same boxes give the same poses.
"""

from __future__ import annotations

import numpy as np

CORNER_TOLERANCE = 1e-6
"""Largest distance (m) of a corner from the box its neighbours span."""

_EPS = 1e-9


def canonical_frames(axes: np.ndarray, extents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reorder and flip box axes into fabflow's element frame (see the module).

    Parameters
    ----------
    axes
        (M, 3, 3) box axes as columns (unit, orthogonal), world frame.
    extents
        (M, 3) box sizes along those axes (m).

    Returns
    -------
    tuple of numpy.ndarray
        (M, 3, 3) rotations R_world_element (columns x, y, z) and (M, 3) extents
        (length along x, width along y, height along z).
    """
    axes = np.asarray(axes, dtype=float)
    extents = np.asarray(extents, dtype=float)
    m = len(axes)
    rows = np.arange(m)
    # each axis signed the way the frame will point it, for the tie-breaks below
    # (two axes equally vertical, or two equal sides equally along world x)
    up = _signed(axes, (2, 0, 1))
    k_z = _first_best(np.abs(axes[:, 2, :]), up[:, 0, :], up[:, 1, :], np.ones((m, 3), bool))
    # the longer horizontal axis is x; on a tie, the one nearer world x
    along = _signed(axes, (0, 1, 2))
    allowed = np.arange(3)[None, :] != k_z[:, None]
    length = np.where(allowed, extents, -np.inf)
    tied = allowed & (length >= length.max(axis=1, keepdims=True) - _EPS)
    k_x = _first_best(np.abs(axes[:, 0, :]), along[:, 1, :], along[:, 2, :], tied)
    z = axes[rows, :, k_z]
    z = z * np.where(z[:, 2] < 0.0, -1.0, 1.0)[:, None]
    x = axes[rows, :, k_x]
    flip = np.where(np.abs(x[:, 0]) > _EPS, x[:, 0] < 0.0, x[:, 1] < 0.0)
    x = x * np.where(flip, -1.0, 1.0)[:, None]
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=2)
    k_y = 3 - k_x - k_z
    ext = np.stack([extents[rows, k_x], extents[rows, k_y], extents[rows, k_z]], axis=1)
    return R, ext


def _signed(axes: np.ndarray, order: tuple[int, int, int]) -> np.ndarray:
    """(M, 3, 3) the axes (columns) flipped so that the first of their world
    components in ``order`` that is not zero is positive, components in that order."""
    comps = axes[:, list(order), :]
    lead = np.where(np.abs(comps[:, 0]) > _EPS, comps[:, 0], comps[:, 1])
    lead = np.where(np.abs(lead) > _EPS, lead, comps[:, 2])
    return comps * np.where(lead < 0.0, -1.0, 1.0)[:, None, :]


def _first_best(
    first: np.ndarray, second: np.ndarray, third: np.ndarray, allowed: np.ndarray
) -> np.ndarray:
    """(M,) the column with the largest ``first`` of those ``allowed`` ((M, 3) each), ties
    (within 1e-9) broken by ``second``, then ``third``: the same column whoever drew it."""
    candidates = allowed.copy()
    for key in (first, second):
        value = np.where(candidates, key, -np.inf)
        candidates &= value >= value.max(axis=1, keepdims=True) - _EPS
    return np.argmax(np.where(candidates, third, -np.inf), axis=1)


def box_pose_from_corners(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Element frames and sizes of boxes given by their eight corners.

    Parameters
    ----------
    corners
        (M, 8, 3) corners of each box in the world frame (m), in any order.

    Returns
    -------
    tuple of numpy.ndarray
        (M, 4, 4) T_world_element and (M, 3) extents (m), see the module.

    Raises
    ------
    ValueError
        When some box's corners are not those of a box with positive sizes
        (within :data:`CORNER_TOLERANCE`); the message names its index.
    """
    corners = np.asarray(corners, dtype=float)
    if corners.ndim != 3 or corners.shape[1:] != (8, 3):
        raise ValueError(f"expected (M, 8, 3) corners, got shape {corners.shape}")
    if not np.isfinite(corners).all():
        raise ValueError("corners must be finite")
    m = len(corners)
    # From one corner, the shortest way to another corner is an edge; the next
    # edges are the shortest ways orthogonal to the edges found (a diagonal is
    # not orthogonal to the edges it spans).
    d = corners[:, 1:, :] - corners[:, :1, :]
    n = np.linalg.norm(d, axis=2)
    unit = d / np.where(n > 0, n, 1.0)[:, :, None]
    rows = np.arange(m)
    free = np.ones((m, 7), dtype=bool)
    picks = []
    for _ in range(3):  # three edges, each a vectorised pick over all boxes
        k = np.argmin(np.where(free, n, np.inf), axis=1)
        picks.append(k)
        ortho = np.abs(np.einsum("mkj,mj->mk", unit, unit[rows, k])) < 1e-6
        free &= ortho
    edges = np.stack([d[rows, k] for k in picks], axis=1)  # (M, 3, 3) rows
    lengths = np.linalg.norm(edges, axis=2)
    bad = lengths.min(axis=1) <= CORNER_TOLERANCE
    axes = np.swapaxes(edges / np.where(lengths > 0, lengths, 1.0)[:, :, None], 1, 2)
    centre = corners.mean(axis=1)
    # Every corner must be centre +- half sizes along the axes.
    local = np.einsum("mji,mkj->mki", axes, corners - centre[:, None, :])
    err = np.abs(np.abs(local) - lengths[:, None, :] / 2.0).max(axis=(1, 2))
    gram = np.einsum("mji,mjk->mik", axes, axes) - np.eye(3)
    bad |= (err > CORNER_TOLERANCE) | (np.abs(gram).max(axis=(1, 2)) > 1e-6)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"box {i}: its 8 corners do not form a box")
    R, extents = canonical_frames(axes, lengths)
    T = np.tile(np.eye(4), (m, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = centre
    return T, extents


def oriented_box_pose(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Element frame and size of the smallest box around a shape (a mesh, a brep).

    Parameters
    ----------
    points
        (N, 3) vertices of the shape in the world frame (m), N >= 4, not all in
        one plane.

    Returns
    -------
    tuple of numpy.ndarray
        (4, 4) T_world_element at the box's centre and (3,) its extents (m).

    Raises
    ------
    ValueError
        For fewer than 4 points, non-finite points or a flat shape.
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise ValueError("a shape needs at least 4 vertices")
    if not np.isfinite(points).all():
        raise ValueError("vertices must be finite")
    spread = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    if spread[-1] <= CORNER_TOLERANCE:
        raise ValueError("the shape is flat (no volume)")
    import trimesh  # heavy; only meshes drawn without a frame need it

    T_box_world, extents = trimesh.bounds.oriented_bounds(points)
    T_world_box = np.linalg.inv(T_box_world)
    R, ext = canonical_frames(T_world_box[None, :3, :3], np.asarray(extents)[None])
    T = np.eye(4)
    T[:3, :3] = R[0]
    T[:3, 3] = T_world_box[:3, 3]
    return T, ext[0]
