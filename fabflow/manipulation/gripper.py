"""A two-jaw gripper as three boxes: two jaws and the palm they are mounted on.

The gripper frame, used by every module of :mod:`fabflow.manipulation`:

* ``z`` is the approach direction, from the palm towards the object;
* ``y`` is the closing direction, the jaws move along ``±y``;
* ``x`` completes the right-handed frame (across the jaws' width);
* the origin is midway between the tips of the jaws.

With the jaws open by ``w`` (the distance between their inner faces, metres), the
``+y`` jaw occupies ``x ∈ [-jaw_width/2, jaw_width/2]``, ``y ∈ [w/2, w/2 + jaw_thickness]``
and ``z ∈ [-jaw_length, 0]``; the ``-y`` jaw is its mirror image; the palm spans the full
``palm_width`` along ``y`` and ``z ∈ [-jaw_length - palm_thickness, -jaw_length]``. The
closing region, the space the jaws sweep when they close, is ``|x| <= jaw_width/2``,
``|y| < w/2`` and ``-jaw_length < z <= 0``.

Poses are 4x4 matrices ``T_world_gripper`` in metres. Paper 002 (section 5) approximates
the gripper by convex polyhedra enclosing jaws and palm; boxes are such polyhedra.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.positioning.pointcloud import as_points

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

JAW_POS, JAW_NEG, PALM = 0, 1, 2
"""Indices of the boxes returned by :func:`gripper_boxes`."""

_CHUNK_ELEMENTS = 2_000_000
"""Largest number of (pose, point) pairs transformed at once by :func:`points_in_boxes`."""
_SWEEP_CHUNK = 500_000
"""Largest (pose, point) table of :func:`sweep_approach` built at once; small enough to
stay in the processor's cache, which makes the sweep several times faster."""


@dataclass(frozen=True)
class TwoJawGripper:
    """Dimensions of a two-jaw gripper (metres), sized for stones of 0.5-1 m³.

    Attributes
    ----------
    max_opening
        Largest distance between the jaws' inner faces.
    min_opening
        Smallest distance between the jaws' inner faces (fully closed).
    jaw_length
        Length of a jaw along the approach ``z``, from its tip to the palm.
    jaw_width
        Width of a jaw along the gripper's ``x``.
    jaw_thickness
        Thickness of a jaw along the closing direction ``y``.
    palm_thickness
        Depth of the palm behind the jaws, along ``-z``.
    palm_width
        Extent of the palm along ``y``; ``None`` means ``max_opening + 2 * jaw_thickness``,
        the span of the fully opened jaws. It may not be smaller than that.
    """

    max_opening: float = 1.6
    min_opening: float = 0.05
    jaw_length: float = 0.7
    jaw_width: float = 0.35
    jaw_thickness: float = 0.08
    palm_thickness: float = 0.25
    palm_width: float | None = None

    def __post_init__(self) -> None:
        for name in (
            "max_opening",
            "jaw_length",
            "jaw_width",
            "jaw_thickness",
            "palm_thickness",
        ):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise InputError(f"gripper {name} must be a positive length in metres, got {value}")
        if not np.isfinite(self.min_opening) or self.min_opening < 0:
            raise InputError(f"gripper min_opening must be >= 0 m, got {self.min_opening}")
        if self.min_opening >= self.max_opening:
            raise InputError(
                f"gripper min_opening ({self.min_opening} m) must be smaller than "
                f"max_opening ({self.max_opening} m)"
            )
        span = self.max_opening + 2.0 * self.jaw_thickness
        if self.palm_width is not None and not (self.palm_width >= span - 1e-12):
            raise InputError(
                f"gripper palm_width ({self.palm_width} m) must hold the open jaws: at least "
                f"max_opening + 2 * jaw_thickness = {span} m"
            )

    @property
    def palm_span(self) -> float:
        """Extent of the palm along ``y`` (metres), with the default filled in."""
        if self.palm_width is None:
            return self.max_opening + 2.0 * self.jaw_thickness
        return float(self.palm_width)

    def check_opening(self, opening: float) -> float:
        """Return ``opening`` (metres) as a float after checking it is in the gripper's range.

        Raises
        ------
        InputError
            If the opening is outside ``[min_opening, max_opening]``.
        """
        w = float(opening)
        if not (self.min_opening - 1e-9 <= w <= self.max_opening + 1e-9):
            raise InputError(
                f"gripper opening {w} m is outside [{self.min_opening}, {self.max_opening}] m"
            )
        return w


def gripper_boxes(gripper: TwoJawGripper, opening: float) -> FloatArray:
    """Corners of the gripper's three boxes in the gripper frame.

    Parameters
    ----------
    gripper
        The gripper's dimensions.
    opening
        Distance between the jaws' inner faces (metres).

    Returns
    -------
    numpy.ndarray
        ``(3, 2, 3)``: for the ``+y`` jaw, the ``-y`` jaw and the palm (indices
        :data:`JAW_POS`, :data:`JAW_NEG`, :data:`PALM`), the lower and upper corner
        (metres, gripper frame).
    """
    w = gripper.check_opening(opening)
    a = gripper.jaw_width / 2.0
    t = gripper.jaw_thickness
    length = gripper.jaw_length
    half_palm = gripper.palm_span / 2.0
    return np.array(
        [
            [[-a, w / 2.0, -length], [a, w / 2.0 + t, 0.0]],
            [[-a, -w / 2.0 - t, -length], [a, -w / 2.0, 0.0]],
            [[-a, -half_palm, -length - gripper.palm_thickness], [a, half_palm, -length]],
        ]
    )


def closing_region(gripper: TwoJawGripper, opening: float) -> FloatArray:
    """Lower and upper corner ``(2, 3)`` of the closing region (metres, gripper frame).

    The region is half-open in the gripper frame: ``|y| < opening/2`` and
    ``-jaw_length < z <= 0``; the corners bound it.
    """
    w = gripper.check_opening(opening)
    a = gripper.jaw_width / 2.0
    return np.array([[-a, -w / 2.0, -gripper.jaw_length], [a, w / 2.0, 0.0]])


def _as_poses(T_world_gripper: ArrayLike) -> FloatArray:
    T = np.asarray(T_world_gripper, dtype=float)
    if T.shape == (4, 4):
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InputError(f"gripper poses must be (K, 4, 4), got shape {T.shape}")
    return T


def points_in_boxes(
    T_world_gripper: ArrayLike, points: ArrayLike, lower: ArrayLike, upper: ArrayLike
) -> BoolArray:
    """Which points lie inside a box fixed to the gripper, for many gripper poses.

    Parameters
    ----------
    T_world_gripper
        ``(K, 4, 4)`` (or one ``(4, 4)``) gripper poses in the world (metres).
    points
        ``(N, 3)`` points in the world (metres).
    lower, upper
        ``(3,)`` corners of the box in the gripper frame (metres), bounds included.

    Returns
    -------
    numpy.ndarray
        ``(K, N)`` booleans. Poses are handled in chunks, so the intermediate
        arrays stay small; only the boolean result has ``K * N`` entries. Use
        :func:`count_points_in_boxes` when the counts suffice.
    """
    T = _as_poses(T_world_gripper)
    p = as_points(points)
    out = np.zeros((len(T), len(p)), dtype=bool)
    for start, inside in _inside_chunks(T, p, lower, upper):
        out[start : start + len(inside)] = inside
    return out


def count_points_in_boxes(
    T_world_gripper: ArrayLike, points: ArrayLike, lower: ArrayLike, upper: ArrayLike
) -> NDArray[np.int64]:
    """Number of points inside a box fixed to the gripper, per pose.

    Same arguments as :func:`points_in_boxes`; returns ``(K,)`` counts without
    building the ``(K, N)`` table.
    """
    T = _as_poses(T_world_gripper)
    p = as_points(points)
    out = np.zeros(len(T), dtype=np.int64)
    for start, inside in _inside_chunks(T, p, lower, upper):
        out[start : start + len(inside)] = inside.sum(axis=1)
    return out


def count_points_in_gripper(
    gripper: TwoJawGripper, T_world_gripper: ArrayLike, openings: ArrayLike, points: ArrayLike
) -> NDArray[np.int64]:
    """Points inside the jaws or the palm, for many gripper poses each at its own opening.

    Parameters
    ----------
    gripper
        The gripper.
    T_world_gripper
        ``(K, 4, 4)`` gripper poses in the world (metres).
    openings
        ``(K,)`` jaw openings (metres), each within the gripper's range.
    points
        ``(N, 3)`` points in the world (metres).

    Returns
    -------
    numpy.ndarray
        ``(K,)`` counts, as :func:`count_points_in_boxes` over the three boxes of
        :func:`gripper_boxes` (bounds included), without a loop over the poses.
    """
    T = _as_poses(T_world_gripper)
    half = 0.5 * np.asarray(openings, dtype=float).reshape(-1)
    if half.shape != (len(T),):
        raise InputError(f"one opening per gripper pose: {len(T)} poses, {half.size} openings")
    p = as_points(points)
    out = np.zeros(len(T), dtype=np.int64)
    step = max(1, _CHUNK_ELEMENTS // max(len(p), 1))
    for start in range(0, len(T), step):
        Tc, hc = T[start : start + step], half[start : start + step, None]
        local = (p[None, :, :] - Tc[:, None, :3, 3]) @ Tc[:, :3, :3]
        x, y, z = np.abs(local[..., 0]), np.abs(local[..., 1]), local[..., 2]
        across = x <= 0.5 * gripper.jaw_width
        jaws = (y >= hc) & (y <= hc + gripper.jaw_thickness) & (z >= -gripper.jaw_length)
        jaws &= z <= 0.0
        palm = (y <= 0.5 * gripper.palm_span) & (z <= -gripper.jaw_length)
        palm &= z >= -gripper.jaw_length - gripper.palm_thickness
        out[start : start + len(Tc)] = (across & (jaws | palm)).sum(axis=1)
    return out


def _inside_chunks(
    T: FloatArray, p: FloatArray, lower: ArrayLike, upper: ArrayLike
) -> Iterator[tuple[int, BoolArray]]:
    """Yield ``(start, (k, N) inside mask)`` for consecutive chunks of poses."""
    lo = np.asarray(lower, dtype=float).reshape(1, 1, 3)
    hi = np.asarray(upper, dtype=float).reshape(1, 1, 3)
    step = max(1, _CHUNK_ELEMENTS // max(len(p), 1))
    for start in range(0, len(T), step):
        Tc = T[start : start + step]
        # q = R^T (p - t), written as (p - t) @ R for all poses of the chunk
        local = (p[None, :, :] - Tc[:, None, :3, 3]) @ Tc[:, :3, :3]
        yield start, np.all((local >= lo) & (local <= hi), axis=2)


def gripper_mesh(gripper: TwoJawGripper, opening: float) -> trimesh.Trimesh:
    """The gripper's three boxes as one mesh in the gripper frame (metres).

    For previews and for collision checks (the mesh is the union of three closed
    boxes, not one watertight solid).
    """
    boxes = gripper_boxes(gripper, opening)
    return trimesh.util.concatenate([trimesh.creation.box(bounds=b) for b in boxes])


def sweep_approach(
    points: ArrayLike,
    anchors: ArrayLike,
    G: ArrayLike,
    gripper: TwoJawGripper,
    standoff: float = 0.0,
) -> tuple[FloatArray, IntArray, IntArray, FloatArray]:
    """Push the gripper, open at ``max_opening``, along its approach until it touches a cloud.

    ``points`` ``(N, 3)``, ``anchors`` ``(K, 3)`` and the gripper orientations ``G``
    ``(K, 3, 3)`` (columns x, y, z) share one frame (metres); pose ``k`` is anchored at
    ``anchors[k]``, where its TCP would be with zero advance. Coming from far behind, a
    point in the footprint of a jaw (``|x| <= jaw_width/2``, ``max_opening/2 <= |y| <=
    max_opening/2 + jaw_thickness``) is touched when the tips reach its depth ``z``; any
    other point under the palm (``|x| <= jaw_width/2``, ``|y| <= palm_width/2``) when the
    palm does, ``jaw_length`` later. The first touch minus ``standoff`` is the final
    advance ``s`` of the TCP from the anchor along ``z``: no point then lies in a jaw or
    the palm.

    Returns
    -------
    s, k, j, v
        ``(K,)`` advances (``inf`` when nothing is touched) and, sorted by pose, the
        (pose, point, ``y``) of the points in the closing region at advance ``s``.
    """
    p = as_points(points)
    anchors = np.asarray(anchors, dtype=float).reshape(-1, 3)
    G = np.asarray(G, dtype=float).reshape(len(anchors), 3, 3)
    a, length = gripper.jaw_width / 2.0, gripper.jaw_length
    half, band = gripper.max_opening / 2.0, gripper.max_opening / 2.0 + gripper.jaw_thickness
    p32 = np.ascontiguousarray(p.T, dtype=np.float32)
    offsets = np.einsum("kij,ki->kj", G, anchors).astype(np.float32)
    G32 = G.astype(np.float32)
    s = np.full(len(G), np.inf)
    ks, js, vs = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0)]
    step = max(1, _SWEEP_CHUNK // max(len(p), 1))
    for start in range(0, len(G), step):
        stop = min(start + step, len(G))
        # einsum, not matmul: a threaded BLAS stalls on these thin products when the
        # processor is shared, while einsum's own loop stays fast
        u, v, w = (
            np.einsum("kc,cn->kn", G32[start:stop, :, i], p32) - offsets[start:stop, i, None]
            for i in range(3)
        )
        outside = np.abs(u) > a
        abs_v = np.abs(v)
        between = abs_v < half
        touch = np.where((abs_v >= half) & (abs_v <= band), w, w + np.float32(length))
        np.copyto(touch, np.float32(np.inf), where=outside | (abs_v > gripper.palm_span / 2.0))
        s_chunk = touch.min(axis=1).astype(float) - standoff
        s[start:stop] = s_chunk
        lim = s_chunk.astype(np.float32)[:, None]
        kk, jj = np.nonzero(~outside & between & (w <= lim) & (w > lim - np.float32(length)))
        ks.append(kk + start)
        js.append(jj)
        vs.append(v[kk, jj].astype(float))
    return s, np.concatenate(ks), np.concatenate(js), np.concatenate(vs)
