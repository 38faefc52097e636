"""Nearest-neighbour correspondences for ICP, searched only where they may have changed.

:func:`fabflow.positioning.icp.icp` spends most of its time in KD-tree searches.
Two things cut them without changing what it converges to:

* :class:`Matches` keeps each source point's nearest target point while the point
  cannot have come closer to another: a search gives its two nearest target
  points at ``d0 <= d1``, and it is searched again only once it has moved by
  ``(d1 - d0) / 2``. The correspondences are those a fresh search would give at
  every pose; near convergence almost no point is searched;
* :func:`levels` gives the nested subsets of the source a stage iterates on
  before it uses every point: the large first moves are made on a few hundred
  points.

Small searches run on one thread (``PARALLEL_QUERY_MIN``), and the helpers avoid
numpy calls that are slow on ``(N, 3)`` arrays (``np.cross``, fancy indexing).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]

SEARCH_REACH = 1.5
"""The KD-tree searches reach this many times the stage's correspondence distance, so
that a source point's nearest target point is known a little beyond it (and a point
without one stays without one while it moves less than the difference)."""
THIN_POINTS = 500
"""Fewest source points a coarse level of a stage uses (:func:`levels`)."""
THIN_FACTOR = 4
"""Each coarse level of a stage uses this many times fewer source points than the next."""
PARALLEL_QUERY_MIN = 10_000
"""Searches for fewer source points than this run on one thread whatever ``workers``
says: starting the threads costs more than they save on small searches (measured
on a shared 2-core machine: about 3 ms to start them, break-even between 3000 and
10 000 points depending on the load)."""
_GOLDEN = 0.5 * (np.sqrt(5.0) - 1.0)


class Matches:
    """Exact nearest target points of the moving source points, searched again only
    where the motion since the last search could have changed them.

    A search returns a point's two nearest target points within ``reach``, at
    distances ``d0 <= d1``. After the point has moved by ``delta`` (metres), the
    nearest is still the same if ``2 delta < d1 - d0`` (triangle inequality), and a
    point with none within ``reach`` still has none within ``dmax`` if
    ``reach - delta > dmax``. Only the other points are searched again, and the
    distances to the nearest points are recomputed at every pose, so the
    correspondences are those a fresh search would give.

    Parameters
    ----------
    tree
        KD-tree over ``points``.
    points
        ``(M, 3)`` target points (metres, target frame).
    n
        Number of source points.
    workers
        Threads for searches of at least ``PARALLEL_QUERY_MIN`` points (``-1``: all
        cores).
    """

    def __init__(self, tree: cKDTree, points: FloatArray, n: int, workers: int) -> None:
        self.tree = tree
        self.points = points
        self.workers = workers
        self.nearest = np.full(n, -1, dtype=np.intp)  # -1: none within the reach
        # squared motion each point can make before its correspondence may change:
        # ((d1 - d0) / 2)^2, or (reach - dmax)^2 without a nearest point
        self.slack2 = np.full(n, -1.0)
        self.anchor = np.full((n, 3), np.inf)  # where each point was at its last search
        self.dmax = np.inf  # the distance of the last call
        self.searched = 0  # points searched so far
        self._step, self._offset = np.empty((n, 3)), np.empty((n, 3))
        self._size2, self._index = np.empty(n), np.empty(n, dtype=np.intp)

    def find(
        self, p: FloatArray, dmax: float, rows: NDArray[np.intp] | None = None
    ) -> tuple[NDArray[np.intp], NDArray[np.intp], FloatArray, FloatArray]:
        """Correspondences of the source points ``rows`` (all when ``None``), now at ``p``.

        Returns
        -------
        at, nearest, offset, distance
            The rows of ``p`` with a target point within ``dmax`` (metres), in
            order; the index of that target point; ``p - q`` (metres, target
            frame); and its length. ``nearest`` and ``offset`` are overwritten by
            the next call.
        """
        if dmax > self.dmax:  # a point without a nearest may now have one
            self.slack2[self.nearest < 0] = -1.0
        self.dmax = dmax
        if rows is None:
            nearest, slack2, anchor = self.nearest, self.slack2, self.anchor
        else:
            nearest, slack2 = np.take(self.nearest, rows), np.take(self.slack2, rows)
            anchor = np.take(self.anchor, rows, axis=0)
        m = len(p)
        step = np.subtract(p, anchor, out=self._step[:m])
        todo = np.flatnonzero(row_dot(step, step, out=self._size2[:m]) >= slack2)
        if len(todo):
            reach = SEARCH_REACH * dmax
            moved = np.take(p, todo, axis=0)
            workers = self.workers if len(todo) >= PARALLEL_QUERY_MIN else 1
            d, j = self.tree.query(moved, k=2, distance_upper_bound=reach, workers=workers)
            found = np.isfinite(d[:, 0])
            new = np.where(found, j[:, 0], -1)
            half = np.where(found, 0.5 * (np.minimum(d[:, 1], reach) - d[:, 0]), reach - dmax)
            nearest[todo] = new
            at = todo if rows is None else rows[todo]
            self.nearest[at] = new
            self.slack2[at] = half * half
            self.anchor[at] = moved
            self.searched += len(todo)
        at = np.flatnonzero(nearest >= 0)
        k = len(at)
        if k == m:  # the common case: no copies
            ii = self._index[:m]
            ii[:] = nearest
            e = np.take(self.points, ii, axis=0, out=self._offset[:m])
            np.subtract(p, e, out=e)
        else:
            ii = np.take(nearest, at, out=self._index[:k])
            e = np.take(self.points, ii, axis=0, out=self._offset[:k])
            np.subtract(np.take(p, at, axis=0), e, out=e)
        d2 = row_dot(e, e, out=self._size2[:k])
        inside = d2 <= dmax * dmax
        if not inside.all():
            keep = np.flatnonzero(inside)
            at, ii, d2 = np.take(at, keep), np.take(ii, keep), np.take(d2, keep)
            e = np.take(e, keep, axis=0)
        return at, ii, e, np.sqrt(d2)


class Workspace:
    """Arrays of ``n`` rows that every iteration of one registration reuses.

    New arrays of this size come from fresh pages of memory, whose faults cost up
    to a quarter of the loop's time (a 14 596-point scan on 2 cores).

    Attributes
    ----------
    moved, normals, cross, nw, cw
        ``(n, 3)``: the source at the current pose, the matched normals, ``p x n``
        and the two weighted.
    """

    def __init__(self, n: int) -> None:
        self.moved, self.normals, self.cross = (np.empty((n, 3)) for _ in range(3))
        self.nw, self.cw = np.empty((n, 3)), np.empty((n, 3))


def levels(n: int) -> list[NDArray[np.intp] | None]:
    """The source rows of each level of a stage, coarse to fine, ending with all (``None``).

    Subsets of about ``n / THIN_FACTOR``, ``n / THIN_FACTOR^2``, ... rows down to
    ``THIN_POINTS``, nested, each in the source's order: the rows ``i`` with
    ``frac(i * golden ratio)`` below the subset's share, which spread over any
    ordering without aliasing with its periods (a scan's channels, a grid's rows;
    Weyl's equidistribution).
    """
    shares: list[float] = []
    share = 1.0 / THIN_FACTOR
    while n * share >= THIN_POINTS:
        shares.append(share)
        share /= THIN_FACTOR
    if not shares:
        return [None]
    phase = (np.arange(n) * _GOLDEN) % 1.0
    return [np.flatnonzero(phase < share) for share in reversed(shares)] + [None]


def transformed(T: FloatArray, points: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """``points`` ``(N, 3)`` moved by ``T`` (:func:`~fabflow.transforms.se3.apply_T`
    without its checks, for the loop), into ``out`` (``(N, 3)``, C order) if given."""
    out = np.dot(points, T[:3, :3].T, out=out)
    out += T[:3, 3]
    return out


def row_dot(a: FloatArray, b: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """Row-wise dot products of two ``(N, 3)`` arrays, into ``out`` (``(N,)``) if given
    (column by column: three times faster than ``np.einsum("ij,ij->i", a, b)``)."""
    out = np.multiply(a[:, 0], b[:, 0], out=out)
    out += a[:, 1] * b[:, 1]
    out += a[:, 2] * b[:, 2]
    return out


def row_cross(a: FloatArray, b: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """Row-wise cross products of two ``(N, 3)`` arrays (``np.cross`` without its
    axis handling, several times faster on such arrays), into ``out`` if given."""
    if out is None:
        out = np.empty_like(a)
    np.multiply(a[:, 1], b[:, 2], out=out[:, 0])
    out[:, 0] -= a[:, 2] * b[:, 1]
    np.multiply(a[:, 2], b[:, 0], out=out[:, 1])
    out[:, 1] -= a[:, 0] * b[:, 2]
    np.multiply(a[:, 0], b[:, 1], out=out[:, 2])
    out[:, 2] -= a[:, 1] * b[:, 0]
    return out
