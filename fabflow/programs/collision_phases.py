"""Broad and narrow phase of the collision check (:mod:`fabflow.programs.collision`).

Broad phase in numpy: pairs of overlapping axis-aligned boxes found through a
plan grid (:func:`aabb_pairs`). Narrow phase with python-fcl: signed distance of a
capsule or box from an obstacle box, after a collision test of the body grown by
the clearance (:class:`Narrow`).
"""

from __future__ import annotations

import fcl
import numpy as np

from fabflow.programs.collision_model import Obstacles


def capsule_frames(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3, 3) rotations with z along ``b - a`` and (n, 3) midpoints of segments."""
    axis = b - a
    length = np.linalg.norm(axis, axis=1)
    z = np.where(
        (length > 1e-12)[:, None], axis / np.maximum(length, 1e-12)[:, None], [0.0, 0.0, 1.0]
    )
    helper = np.where((np.abs(z[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x, axis=1)[:, None]
    return np.stack([x, np.cross(z, x), z], axis=2), 0.5 * (a + b)


LENGTH_STEP = 1e-9
"""Capsule lengths are rounded to this (metres) to share fcl objects between samples."""


class Narrow:
    """fcl objects of one check: obstacle boxes, and per body a true-size object and
    one grown by the clearance (a hit of the grown one is a candidate contact).

    A capsule's length is its segment's at the sample (rounded to :data:`LENGTH_STEP`):
    a link across a prismatic joint changes length with it.
    """

    def __init__(self, obs: Obstacles, radii: np.ndarray, clearance: float):
        self.obs = obs
        self.clearance = clearance
        self.radii = np.asarray(radii, dtype=float)
        self.boxes: dict[int, fcl.CollisionObject] = {}
        self.capsules: dict[tuple[int, int], tuple[fcl.CollisionObject, fcl.CollisionObject]] = {}
        self.held: dict[tuple[float, ...], tuple[fcl.CollisionObject, fcl.CollisionObject]] = {}
        self.request = fcl.CollisionRequest()
        self.distance_request = fcl.DistanceRequest(enable_signed_distance=True)

    def _box(self, k: int) -> fcl.CollisionObject:
        if k not in self.boxes:
            T, extents = self.obs.T[k], self.obs.extents[k]
            self.boxes[k] = fcl.CollisionObject(
                fcl.Box(*map(float, extents)), fcl.Transform(T[:3, :3], T[:3, 3])
            )
        return self.boxes[k]

    def _capsule(self, body: int, length: float) -> tuple[fcl.CollisionObject, fcl.CollisionObject]:
        key = (body, round(length / LENGTH_STEP))
        if key not in self.capsules:
            r, n = float(self.radii[body]), key[1] * LENGTH_STEP
            self.capsules[key] = (
                fcl.CollisionObject(fcl.Capsule(r, n)),
                fcl.CollisionObject(fcl.Capsule(r + self.clearance, n)),
            )
        return self.capsules[key]

    def _held(self, extents: np.ndarray) -> tuple[fcl.CollisionObject, fcl.CollisionObject]:
        key = tuple(np.round(extents, 9).tolist())
        if key not in self.held:
            grown = extents + 2.0 * self.clearance
            self.held[key] = (
                fcl.CollisionObject(fcl.Box(*map(float, extents))),
                fcl.CollisionObject(fcl.Box(*map(float, grown))),
            )
        return self.held[key]

    def distance(
        self,
        k: int,
        body: int,
        R: np.ndarray,
        t: np.ndarray,
        extents: np.ndarray | None,
        length: float = 0.0,
    ) -> float:
        """Signed distance of a body at (R, t) from obstacle k, or +inf when the body
        grown by the clearance does not touch it: a capsule of segment ``length``
        (metres), or a held box of ``extents``."""
        true, grown = self._capsule(body, length) if extents is None else self._held(extents)
        box = self._box(k)
        transform = fcl.Transform(R, t)
        grown.setTransform(transform)
        if not fcl.collide(grown, box, self.request, fcl.CollisionResult()):
            return np.inf
        true.setTransform(transform)
        return float(fcl.distance(true, box, self.distance_request, fcl.DistanceResult()))


def ranges(counts: np.ndarray) -> np.ndarray:
    """0..c-1 for every c in ``counts``, concatenated."""
    return np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)


def aabb_pairs(
    a_lo: np.ndarray, a_hi: np.ndarray, b_lo: np.ndarray, b_hi: np.ndarray, cell: float
) -> tuple[np.ndarray, np.ndarray]:
    """Every pair of overlapping axis-aligned boxes between two sets, by a plan grid.

    Each box is entered in the grid cells (``cell`` metres, in x and y) it covers;
    boxes sharing a cell are candidate pairs, kept once (in the cell holding the
    corner ``max(a_lo, b_lo)``) when they overlap in x, y and z.

    Returns
    -------
    ia, ib
        Indices into the a and b sets of the overlapping pairs.
    """
    empty = np.zeros(0, dtype=np.intp)
    if not len(a_lo) or not len(b_lo):
        return empty, empty
    finite = np.all(np.isfinite(a_lo) & np.isfinite(a_hi), axis=1)
    if not finite.any():
        return empty, empty
    lo_cell = np.floor(a_lo[finite, :2].min(axis=0) / cell).astype(np.int64)
    hi_cell = np.floor(a_hi[finite, :2].max(axis=0) / cell).astype(np.int64)
    span = hi_cell - lo_cell + 1

    def cells(lo: np.ndarray, hi: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        i0 = np.clip(np.floor(lo[rows, :2] / cell).astype(np.int64) - lo_cell, 0, span - 1)
        i1 = np.clip(np.floor(hi[rows, :2] / cell).astype(np.int64) - lo_cell, 0, span - 1)
        ny = i1[:, 1] - i0[:, 1] + 1
        n = (i1[:, 0] - i0[:, 0] + 1) * ny
        owner = np.repeat(np.arange(len(rows)), n)
        j = ranges(n)
        key = (i0[owner, 0] + j // ny[owner]) * span[1] + i0[owner, 1] + j % ny[owner]
        return rows[owner], key

    rows_a = np.flatnonzero(finite)
    outside = np.any(b_hi[:, :2] < (lo_cell * cell), axis=1) | np.any(
        b_lo[:, :2] > ((hi_cell + 1) * cell), axis=1
    )
    rows_b = np.flatnonzero(~outside)
    ao, akey = cells(a_lo, a_hi, rows_a)
    bo, bkey = cells(b_lo, b_hi, rows_b)
    order = np.argsort(bkey, kind="stable")
    bkey, bo = bkey[order], bo[order]
    left = np.searchsorted(bkey, akey, side="left")
    n = np.searchsorted(bkey, akey, side="right") - left
    ia = np.repeat(ao, n)
    key = np.repeat(akey, n)
    ib = bo[np.repeat(left, n) + ranges(n)]
    # overlap one axis at a time on contiguous columns, dropping pairs as they fail
    for axis in range(3):
        keep = (a_lo[:, axis][ia] <= b_hi[:, axis][ib]) & (a_hi[:, axis][ia] >= b_lo[:, axis][ib])
        ia, ib, key = ia[keep], ib[keep], key[keep]
    ref = [
        np.clip(
            np.floor(np.maximum(a_lo[:, axis][ia], b_lo[:, axis][ib]) / cell).astype(np.int64)
            - lo_cell[axis],
            0,
            span[axis] - 1,
        )
        for axis in range(2)
    ]
    once = ref[0] * span[1] + ref[1] == key
    return ia[once], ib[once]
