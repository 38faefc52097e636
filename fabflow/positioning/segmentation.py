"""Map segmentation into objects (paper 002, section 4.3 and Table 3).

The pipeline: voxelize the map (``res_voxel`` = 3 cm, ``n_min`` = 1), remove the
ground with a RANSAC plane fit (distance margin ``d_plane`` = 10 cm, restricted to
near-horizontal planes), grow segments by Euclidean clustering (connected
components of the graph of points closer than ``cluster_distance``), and discard
nearly planar segments with a RANSAC planarity check (they are usually ground or
walls the ground fit missed). What remains are the objects: each segment's points
and centroid go into an object table.

All steps are vectorized: RANSAC scores all hypotheses in one array operation,
clustering uses :meth:`scipy.spatial.cKDTree.query_pairs` and
:func:`scipy.sparse.csgraph.connected_components`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from fabflow.positioning.pointcloud import as_points, voxel_downsample

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SegmentationParams:
    """Parameters of the perception pipeline (defaults: paper 002, Table 3).

    Attributes
    ----------
    voxel_size
        ``res_voxel``: voxel grid of the map (metres).
    min_points_per_voxel
        ``n_min``: voxels with fewer points are empty.
    plane_distance
        ``d_plane``: RANSAC ground plane distance margin (metres).
    max_ground_tilt_deg
        Only planes whose normal is within this angle of +z count as ground.
    cluster_distance
        Points closer than this are in the same segment (metres).
    min_segment_points, max_segment_points
        Segments outside this size range are dropped.
    planar_inlier_ratio
        A segment whose best RANSAC plane (margin ``planar_distance``) holds more
        than this fraction of its points is "nearly planar" and discarded.
    planar_distance
        Distance margin of the planarity check (metres).
    ransac_iterations
        Plane hypotheses drawn per RANSAC fit.
    """

    voxel_size: float = 0.03
    min_points_per_voxel: int = 1
    plane_distance: float = 0.10
    max_ground_tilt_deg: float = 20.0
    cluster_distance: float = 0.10
    min_segment_points: int = 50
    max_segment_points: int = 2_000_000
    planar_inlier_ratio: float = 0.9
    planar_distance: float = 0.05
    ransac_iterations: int = 300


@dataclass(frozen=True, eq=False)
class Segment:
    """One object found in the map.

    Attributes
    ----------
    id
        Index in the object table.
    points
        ``(n, 3)`` the segment's points (map frame, metres).
    centroid
        Mean of the points (metres).
    lower, upper
        Axis-aligned bounds (metres).
    """

    id: int
    points: FloatArray
    centroid: FloatArray
    lower: FloatArray
    upper: FloatArray

    def to_dict(self) -> dict[str, Any]:
        """One row of the object table (JSON-compatible; points left out)."""
        return {
            "id": self.id,
            "n_points": len(self.points),
            "centroid": self.centroid.tolist(),
            "lower": self.lower.tolist(),
            "upper": self.upper.tolist(),
        }


@dataclass(frozen=True, eq=False)
class Segmentation:
    """The result of :func:`segment_map`.

    Attributes
    ----------
    points
        The voxelized map the labels refer to.
    ground_plane
        ``(a, b, c, d)`` with ``a x + b y + c z + d = 0``, unit normal pointing up.
    ground
        Boolean mask of ground points.
    labels
        Segment id per point, ``-1`` for ground, dropped and planar points.
    segments
        The non-planar segments (the object table).
    n_planar
        Number of segments discarded as nearly planar.
    """

    points: FloatArray
    ground_plane: FloatArray
    ground: NDArray[np.bool_]
    labels: NDArray[np.int64]
    segments: list[Segment] = field(default_factory=list)
    n_planar: int = 0

    @property
    def centroids(self) -> FloatArray:
        """``(k, 3)`` segment centroids."""
        if not self.segments:
            return np.zeros((0, 3))
        return np.stack([s.centroid for s in self.segments])

    def object_table(self) -> list[dict[str, Any]]:
        """The segments as JSON-compatible rows."""
        return [s.to_dict() for s in self.segments]


def _planes_from_triples(p: FloatArray) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Unit normals, offsets and validity of planes through ``(k, 3, 3)`` point triples."""
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n = n / np.where(ok, norm, 1.0)[:, None]
    d = -np.einsum("ij,ij->i", n, p[:, 0])
    return n, d, ok


def ransac_plane(
    points: ArrayLike,
    distance: float,
    rng: np.random.Generator,
    iterations: int = 300,
    max_tilt_deg: float | None = None,
    sample: int = 20_000,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Fit a plane with RANSAC, then refine it by least squares on its inliers.

    Parameters
    ----------
    points
        ``(N, 3)`` points (metres), N >= 3.
    distance
        Inlier margin (metres).
    rng
        Draws the hypotheses.
    iterations
        Number of three-point hypotheses, all scored at once.
    max_tilt_deg
        Only planes whose normal is within this angle of +z are accepted.
    sample
        Hypotheses are scored on at most this many points (a random subset).

    Returns
    -------
    plane, inliers
        ``(a, b, c, d)`` (unit normal, ``c >= 0``) and the inlier mask over ``points``.
        A zero plane and an empty mask when no valid hypothesis exists.
    """
    p = as_points(points)
    if len(p) < 3:
        return np.zeros(4), np.zeros(len(p), dtype=bool)
    idx = rng.integers(0, len(p), (iterations, 3))
    n, d, ok = _planes_from_triples(p[idx])
    if max_tilt_deg is not None:
        ok &= np.abs(n[:, 2]) >= np.cos(np.radians(max_tilt_deg))
    if not ok.any():
        return np.zeros(4), np.zeros(len(p), dtype=bool)
    n, d = n[ok], d[ok]
    sub = p if len(p) <= sample else p[rng.choice(len(p), sample, replace=False)]
    counts = np.zeros(len(n), dtype=np.int64)
    for start in range(0, len(n), 64):  # chunks bound the memory of the (k, N) distances
        dist = np.abs(sub @ n[start : start + 64].T + d[start : start + 64])
        counts[start : start + 64] = (dist <= distance).sum(axis=0)
    best = int(np.argmax(counts))
    inliers = np.abs(p @ n[best] + d[best]) <= distance
    q = p[inliers]
    c = q.mean(axis=0)
    normal = np.linalg.svd(q - c, full_matrices=False)[2][-1]
    if normal[2] < 0:
        normal = -normal
    plane = np.append(normal, -normal @ c)
    inliers = np.abs(p @ plane[:3] + plane[3]) <= distance
    return plane, inliers


def euclidean_clusters(
    points: ArrayLike, distance: float, min_points: int = 1, max_points: int | None = None
) -> NDArray[np.int64]:
    """Label connected groups of points closer than ``distance`` (metres).

    Returns
    -------
    numpy.ndarray
        ``(N,)`` cluster label per point, numbered by decreasing size from 0;
        ``-1`` for points in clusters outside ``[min_points, max_points]``.
    """
    p = as_points(points)
    if len(p) == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = cKDTree(p).query_pairs(distance, output_type="ndarray")
    graph = coo_matrix(
        (np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(len(p), len(p))
    )
    _, raw = connected_components(graph, directed=False)
    sizes = np.bincount(raw)
    keep = sizes >= min_points
    if max_points is not None:
        keep &= sizes <= max_points
    order = np.argsort(-sizes, kind="stable")
    order = order[keep[order]]
    remap = np.full(len(sizes), -1, dtype=np.int64)
    remap[order] = np.arange(len(order))
    return remap[raw]


def segment_map(
    points: ArrayLike,
    rng: np.random.Generator,
    params: SegmentationParams = SegmentationParams(),
) -> Segmentation:
    """Segment a map into objects: voxelize, remove ground, cluster, drop planar segments.

    Parameters
    ----------
    points
        ``(N, 3)`` map points (metres, z up).
    rng
        Draws the RANSAC hypotheses.
    params
        Pipeline parameters (paper 002, Table 3 by default).
    """
    p, _ = voxel_downsample(points, params.voxel_size, min_points=params.min_points_per_voxel)
    plane, ground = ransac_plane(
        p,
        params.plane_distance,
        rng,
        params.ransac_iterations,
        max_tilt_deg=params.max_ground_tilt_deg,
    )
    rest = np.flatnonzero(~ground)
    raw = euclidean_clusters(
        p[rest], params.cluster_distance, params.min_segment_points, params.max_segment_points
    )
    labels = np.full(len(p), -1, dtype=np.int64)
    segments: list[Segment] = []
    n_planar = 0
    for k in range(int(raw.max()) + 1 if len(raw) else 0):
        members = rest[raw == k]
        q = p[members]
        _, inl = ransac_plane(q, params.planar_distance, rng, params.ransac_iterations)
        if inl.mean() > params.planar_inlier_ratio:
            n_planar += 1
            continue
        sid = len(segments)
        labels[members] = sid
        segments.append(Segment(sid, q, q.mean(axis=0), q.min(axis=0), q.max(axis=0)))
    return Segmentation(
        points=p,
        ground_plane=plane,
        ground=ground,
        labels=labels,
        segments=segments,
        n_planar=n_planar,
    )
