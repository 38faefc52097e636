"""Where a UWB platform stands against its anchors: the coverage checks of a fix.

The PDOP of the anchors a fix used and how far outside their convex hull in
plan the platform stands (metres); beyond :data:`COVERAGE_MARGIN` a fix fails
its tests. Anchor planning (:mod:`fabflow.localize.anchors`) places anchors so
that no station stands there.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.spatial import ConvexHull

COVERAGE_MARGIN = 0.5
"""How far (metres, in plan) a platform may stand outside the anchors' convex hull
before its fix fails: outside, the geometry degrades fast and the linearized
covariance no longer describes the error."""


def geometry_checks(A: np.ndarray, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PDOP of the anchors used at each platform, and how far outside their plan hull it stands.

    Parameters
    ----------
    A
        (n, 3) the anchors the fixes used (world, metres).
    states
        (k, 4) the fixes ``[x, y, z, yaw]`` (world, metres and radians).

    Returns
    -------
    pdop, outside
        (k,) each: the PDOPs and the distances outside the hull (metres; 0 inside).
    """
    u = states[:, None, :3] - A
    u /= np.maximum(np.linalg.norm(u, axis=2), 1e-9)[..., None]
    info = np.swapaxes(u, 1, 2) @ u
    pdop = np.sqrt(np.trace(np.linalg.pinv(info), axis1=1, axis2=2))
    return pdop, outside_hull(A[:, :2], states[:, :2])


def outside_hull(anchors_xy: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    """How far (metres) each plan point ``(m, 2)`` lies outside the convex hull of the
    anchors ``(n, 2)``: 0 inside; 0 for all when the anchors span no area."""
    xy = np.asarray(anchors_xy, dtype=float)
    p = np.asarray(points_xy, dtype=float).reshape(-1, 2)
    outside = np.zeros(len(p))
    hull = _plan_hull(xy.tobytes(), len(xy))
    if hull is None:
        return outside
    equations, vertices = hull
    out = (p @ equations[:, :2].T + equations[:, 2]).max(axis=1) > 0
    if out.any():
        v = xy[vertices]
        a, ab = v, np.roll(v, -1, axis=0) - v
        q = p[out][:, None, :]
        t = np.clip(np.einsum("mij,ij->mi", q - a, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
        outside[out] = np.linalg.norm(a + t[..., None] * ab - q, axis=2).min(axis=1)
    return outside


@functools.lru_cache(maxsize=256)
def _plan_hull(xy_bytes: bytes, n: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The plan hull of ``n`` anchors (their ``(n, 2)`` float64 bytes): its facets'
    equations and its vertices in order, or None where they span no area. Made
    once per anchor set: a run's visits mostly use the same anchors."""
    xy = np.frombuffer(xy_bytes, dtype=float).reshape(n, 2)
    if n < 3 or np.linalg.matrix_rank(xy - xy.mean(axis=0)) < 2:
        return None
    hull = ConvexHull(xy)
    equations, vertices = hull.equations.copy(), hull.vertices.copy()
    equations.flags.writeable = vertices.flags.writeable = False
    return equations, vertices
