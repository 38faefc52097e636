"""Oriented boxes (a structure of blocks) and the two tests every planner asks of them.

:func:`boxes_overlap` (separating axes) tells whether an axis-aligned box, such
as a tool's bounding box, touches any block; :func:`segments_clear` whether a
straight segment, such as a line of sight or a UWB range, misses every block.
Frame-agnostic: boxes and queries in one frame, metres.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Boxes:
    """Oriented boxes (the structure built so far) in the base frame.

    Attributes
    ----------
    T_base_box
        ``(k, 4, 4)`` box centre frames.
    extents
        ``(k, 3)`` full side lengths along the box axes (metres).
    """

    T_base_box: np.ndarray
    extents: np.ndarray

    @classmethod
    def empty(cls) -> Boxes:
        """No obstacles."""
        return cls(np.zeros((0, 4, 4)), np.zeros((0, 3)))

    def __len__(self) -> int:
        return int(self.extents.shape[0])


def boxes_overlap(centers: np.ndarray, half_extents: np.ndarray, boxes: Boxes) -> np.ndarray:
    """Whether axis-aligned boxes at ``centers`` overlap any oriented box (separating axes).

    Parameters
    ----------
    centers
        ``(m, 3)`` centres of the axis-aligned (base frame) boxes.
    half_extents
        ``(3,)`` half side lengths of those boxes.
    boxes
        The oriented obstacles.

    Returns
    -------
    numpy.ndarray
        ``(m,)`` boolean.
    """
    m = centers.shape[0]
    if len(boxes) == 0:
        return np.zeros(m, dtype=bool)
    R = boxes.T_base_box[:, :3, :3]
    eb = 0.5 * boxes.extents
    ha = np.asarray(half_extents, dtype=float)
    A = np.broadcast_to(np.eye(3), R.shape)
    B = np.swapaxes(R, 1, 2)  # rows: box axes in the base frame
    cross = np.cross(A[:, :, None, :], B[:, None, :, :]).reshape(-1, 9, 3)
    axes = np.concatenate([A, B, cross], axis=1)  # (k, 15, 3)
    rA = np.abs(axes) @ ha  # (k, 15)
    rB = np.einsum("kab,kb->ka", np.abs(np.einsum("kai,kbi->kab", axes, B)), eb)
    d = boxes.T_base_box[None, :, :3, 3] - centers[:, None, :]  # (m, k, 3)
    sep = np.abs(np.einsum("mki,kai->mka", d, axes)) > (rA + rB)[None] + 1e-12
    return np.any(~np.any(sep, axis=2), axis=1)


def segments_hit(starts: np.ndarray, ends: np.ndarray, boxes: Boxes) -> np.ndarray:
    """Whether segments ``starts -> ends`` ((m, 3); ``starts`` may be (3,)) cross any box."""
    ends = np.asarray(ends, dtype=float).reshape(-1, 3)
    starts = np.broadcast_to(np.asarray(starts, dtype=float), ends.shape)
    return ~segments_clear(starts, ends, boxes)


CLUSTER_CELL = 1.0
"""Edge (metres) of the cells that group boxes for the coarse test of :func:`segments_clear`."""


def _near_segments(
    starts: np.ndarray, ends: np.ndarray, centre: np.ndarray, radius: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (segment, sphere) where the segment passes within the sphere's radius."""
    d = ends - starts
    t = np.clip(
        np.einsum("skc,sc->sk", centre[None] - starts[:, None], d)
        / np.maximum(np.einsum("sc,sc->s", d, d), 1e-12)[:, None],
        0.0,
        1.0,
    )
    closest = starts[:, None] + t[..., None] * d[:, None]
    gap2 = np.einsum("skc,skc->sk", closest - centre[None], closest - centre[None])
    return np.nonzero(gap2 <= (radius * radius)[None])


def segments_clear(starts: np.ndarray, ends: np.ndarray, boxes: Boxes) -> np.ndarray:
    """Whether each segment ``starts[i] -> ends[i]`` misses every box, ``(p,)`` bool.

    A two-level test: the boxes are grouped by the :data:`CLUSTER_CELL` cell
    their centre lies in, each group bounded by a sphere; a segment is tested
    against the boxes' own bounding spheres only in the groups it passes, and
    by the exact slab test only against the boxes it passes near. A site of a
    few thousand candidate set-ups against a whole building stays cheap.
    """
    starts = np.asarray(starts, dtype=float).reshape(-1, 3)
    blocked = np.zeros(len(starts), dtype=bool)
    for seg, t0, t1 in _slab_spans(starts, ends, boxes):
        np.logical_or.at(blocked, seg, t0 < t1)
    return ~blocked


def segments_inside(starts: np.ndarray, ends: np.ndarray, boxes: Boxes) -> np.ndarray:
    """Length (metres) of each segment ``starts[i] -> ends[i]`` inside the boxes, ``(p,)``.

    Summed over the boxes (where boxes overlap, their common part counts once
    per box); the same culling as :func:`segments_clear`.
    """
    starts = np.asarray(starts, dtype=float).reshape(-1, 3)
    ends = np.asarray(ends, dtype=float).reshape(-1, 3)
    length = np.zeros(len(starts))
    span = np.linalg.norm(ends - starts, axis=1)
    for seg, t0, t1 in _slab_spans(starts, ends, boxes):
        np.add.at(length, seg, np.maximum(t1 - t0, 0.0) * span[seg])
    return length


def _cell_keys(points: np.ndarray) -> np.ndarray:
    """One integer per :data:`CLUSTER_CELL` cell of each point, ordered as the cells'
    indices are, lexicographically (``np.unique`` over rows, without its row view)."""
    cells = np.floor(points / CLUSTER_CELL)
    if not np.isfinite(cells).all():  # a box off the map keeps its own group: rows
        return np.unique(cells, axis=0, return_inverse=True)[1].ravel()
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1.0
    if float(np.prod(span)) >= 2.0**62:  # a site too large for one integer: rows
        return np.unique(cells, axis=0, return_inverse=True)[1].ravel()
    c = cells.astype(np.int64)
    return (c[:, 0] * int(span[1]) + c[:, 1]) * int(span[2]) + c[:, 2]


GROUPS_CACHED = 20_000
"""Most boxes whose groups :func:`segments_clear` keeps for the next call (64 sets at
most): a larger structure's are made at each call, so the cache stays a few MB."""


@functools.lru_cache(maxsize=64)
def _groups(
    centre_bytes: bytes, extents_bytes: bytes, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The boxes' groups for :func:`segments_clear`, from their ``(n, 3)`` centres and
    ``(n, 3)`` extents (float64 bytes): each box's bounding radius, the boxes in group
    order, where each group starts in it, and each group's centre and bounding radius
    (read only). Made once per set of boxes: a simulated run tests its tags' lines of
    sight at every visit against the structure then standing, the same in every run."""
    centre = np.frombuffer(centre_bytes, dtype=float).reshape(n, 3)
    radius = 0.5 * np.linalg.norm(np.frombuffer(extents_bytes, dtype=float).reshape(n, 3), axis=1)
    _, group = np.unique(_cell_keys(centre), return_inverse=True)
    group = group.ravel()
    order = np.argsort(group, kind="stable")
    first = np.searchsorted(group[order], np.arange(group.max() + 2))
    # each group's mean centre (any point would do: the radius below encloses the group)
    n_groups = group.max() + 1
    g_centre = (
        np.add.reduceat(centre[order], first[:n_groups], axis=0) / np.diff(first)[:n_groups, None]
    )
    g_radius = np.zeros(len(g_centre))
    np.maximum.at(g_radius, group, np.linalg.norm(centre - g_centre[group], axis=1) + radius)
    for a in (radius, order, first, g_centre, g_radius):
        a.flags.writeable = False
    return radius, order, first, g_centre, g_radius


def _slab_spans(
    starts: np.ndarray, ends: np.ndarray, boxes: Boxes
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per chunk of segments, the (segment, box) pairs that pass near each other: the
    segment indices and the parameters ``t0, t1`` in [0, 1] where the segment enters
    and leaves the box (``t0 >= t1``: it misses)."""
    starts = np.asarray(starts, dtype=float).reshape(-1, 3)
    ends = np.asarray(ends, dtype=float).reshape(-1, 3)
    if len(boxes) == 0 or len(starts) == 0:
        return
    centre = np.ascontiguousarray(boxes.T_base_box[:, :3, 3], dtype=float)
    extents = np.ascontiguousarray(boxes.extents, dtype=float)
    R = boxes.T_base_box[:, :3, :3]
    half = 0.5 * extents
    groups = _groups if len(extents) <= GROUPS_CACHED else _groups.__wrapped__
    radius, order, first, g_centre, g_radius = groups(
        centre.tobytes(), extents.tobytes(), len(extents)
    )
    chunk = max(1, 4_000_000 // max(len(g_centre), 1))
    for lo in range(0, len(starts), chunk):
        s, e = starts[lo : lo + chunk], ends[lo : lo + chunk]
        seg_g, g = _near_segments(s, e, g_centre, g_radius)
        if len(seg_g) == 0:
            continue
        # every box of every group a segment passes
        count = first[g + 1] - first[g]
        seg = np.repeat(seg_g, count)
        box = order[
            np.repeat(first[g], count)
            + np.arange(count.sum())
            - np.repeat(np.cumsum(count) - count, count)
        ]
        d = e[seg] - s[seg]
        t = np.clip(
            np.einsum("kc,kc->k", centre[box] - s[seg], d)
            / np.maximum(np.einsum("kc,kc->k", d, d), 1e-12),
            0.0,
            1.0,
        )
        near = np.linalg.norm(s[seg] + t[:, None] * d - centre[box], axis=1) <= radius[box]
        seg, box = seg[near], box[near]
        if len(seg) == 0:
            continue
        # the segment in the box's frame; slab test
        p0 = np.einsum("kji,kj->ki", R[box], s[seg] - centre[box])
        p1 = np.einsum("kji,kj->ki", R[box], e[seg] - centre[box])
        direction = p1 - p0
        parallel = np.abs(direction) < 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (-half[box] - p0) / direction
            tb = (half[box] - p0) / direction
        inside = np.abs(p0) <= half[box]
        tmin = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
        tmax = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
        yield lo + seg, np.maximum(tmin.max(axis=1), 0.0), np.minimum(tmax.min(axis=1), 1.0)
