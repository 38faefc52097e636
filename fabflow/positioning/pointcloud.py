"""Point cloud basics: voxel downsampling, normals, crops, outlier removal.

A point cloud is an ``(N, 3)`` float array of points in metres, in whatever frame
the caller names (``points_lidar``, ``points_world``); normals, when present, are a
second ``(N, 3)`` array of unit vectors in the same frame. Every function is
vectorized and uses :class:`scipy.spatial.cKDTree` with all cores for neighbour
searches.

Reading and writing files is :mod:`fabflow.positioning.pointcloud_io`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from fabflow.errors import InputError

FloatArray = NDArray[np.float64]

NORMALS_CHUNK = 32_768
"""Points whose normals :func:`estimate_normals` computes at once (bounds the memory
of their neighbourhoods: ``k`` times this many points)."""


def as_points(points: ArrayLike, name: str = "points") -> FloatArray:
    """Check and convert an ``(N, 3)`` array of finite points.

    Raises
    ------
    InputError
        If the shape is not ``(N, 3)`` or a value is not finite.
    """
    a = np.asarray(points, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{name} must be an (N, 3) array of points, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} holds non-finite values (NaN or inf)")
    return a


# ------------------------------------------------------------------------- filters


def voxel_downsample(
    points: ArrayLike,
    voxel_size: float,
    normals: ArrayLike | None = None,
    min_points: int = 1,
) -> tuple[FloatArray, FloatArray | None]:
    """Replace the points of each occupied voxel by their centroid.

    Parameters
    ----------
    points
        ``(N, 3)`` points (metres).
    voxel_size
        Edge length of the cubic voxels (metres, > 0).
    normals
        Optional ``(N, 3)`` normals, averaged per voxel and re-normalized. The
        average ignores their sign (each is flipped to make its largest component
        positive first), so the returned normals are unoriented.
    min_points
        Voxels holding fewer points are dropped (``n_min`` of paper 002, Table 3).

    Returns
    -------
    points, normals
        The voxel centroids (in order of voxel key) and their normals (or ``None``).
    """
    p = as_points(points)
    if voxel_size <= 0:
        raise InputError(f"voxel_size must be positive, got {voxel_size}")
    if len(p) == 0:
        return p.copy(), None if normals is None else np.zeros((0, 3))
    keys = np.floor((p - p.min(axis=0)) / voxel_size).astype(np.int64)
    span = keys.max(axis=0) + 1
    if np.prod(span.astype(float)) < 2**62:
        flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
        _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    n_vox = len(counts)
    sums = np.stack([np.bincount(inverse, weights=p[:, i], minlength=n_vox) for i in range(3)], 1)
    keep = counts >= min_points
    out = sums[keep] / counts[keep, None]
    out_n = None
    if normals is not None:
        n = np.asarray(normals, dtype=float)
        # sign-invariant average: normals of one surface may point either way (PCA
        # normals of a wall), so flip each to make its largest component positive
        big = np.take_along_axis(n, np.argmax(np.abs(n), axis=1)[:, None], axis=1)
        n = np.where(big < 0, -n, n)
        ns = np.stack([np.bincount(inverse, weights=n[:, i], minlength=n_vox) for i in range(3)], 1)
        ns = ns[keep]
        norm = np.linalg.norm(ns, axis=1, keepdims=True)
        out_n = ns / np.where(norm > 0, norm, 1.0)
    return out, out_n


def _smallest_eigenvectors(cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The eigenvalues ``(N, 3)``, ascending, of symmetric positive semi-definite
    ``(N, 3, 3)`` matrices, and the unit eigenvector ``(N, 3)`` of the smallest.

    Closed form, several times faster than ``np.linalg.eigh`` on many small
    matrices: the eigenvalues by the trigonometric solution of the characteristic
    cubic (Smith 1961), the eigenvector as the longest cross product of two rows
    of ``C - l0 I``. Where the two smallest eigenvalues nearly coincide (a line,
    or a point repeated) the cross products vanish and ``eigh`` decides.
    """
    a, b, c = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    d, e, f = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    q = (a + b + c) / 3.0
    aq, bq, cq = a - q, b - q, c - q
    p2 = (aq * aq + bq * bq + cq * cq + 2.0 * (d * d + e * e + f * f)) / 6.0
    p = np.sqrt(p2)
    det = aq * (bq * cq - f * f) - d * (d * cq - f * e) + e * (d * f - bq * e)
    cos3 = np.clip(det / (2.0 * np.where(p > 0, p, 1.0) ** 3), -1.0, 1.0)
    phi = np.arccos(cos3) / 3.0
    l2 = q + 2.0 * p * np.cos(phi)
    l0 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    evals = np.stack([l0, 3.0 * q - l0 - l2, l2], axis=1)
    # rows of C - l0 I: (a - l0, d, e), (d, b - l0, f), (e, f, c - l0)
    al, bl, cl = a - l0, b - l0, c - l0
    cands = np.stack(
        [
            np.stack([d * f - e * bl, e * d - al * f, al * bl - d * d], axis=1),
            np.stack([d * cl - e * f, e * e - al * cl, al * f - d * e], axis=1),
            np.stack([bl * cl - f * f, f * e - d * cl, d * f - bl * e], axis=1),
        ],
        axis=1,
    )
    size2 = np.einsum("nkd,nkd->nk", cands, cands)
    best = np.argmax(size2, axis=1)
    rows = np.arange(len(cov))
    vec = cands[rows, best]
    size = np.sqrt(size2[rows, best])
    vec /= np.where(size > 0, size, 1.0)[:, None]
    weak = size <= 1e-9 * p2  # (l1 - l0) (l2 - l0) tiny: no direction stands out
    if weak.any():
        evals[weak], evecs = np.linalg.eigh(cov[weak])
        vec[weak] = evecs[:, :, 0]
    return evals, vec


def estimate_normals(
    points: ArrayLike,
    k: int = 20,
    viewpoint: ArrayLike | None = None,
    tree: cKDTree | None = None,
    return_planarity: bool = False,
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """Surface normals by PCA over the ``k`` nearest neighbours, oriented.

    Parameters
    ----------
    points
        ``(N, 3)`` points (metres), N >= 3.
    k
        Neighbourhood size (including the point itself).
    viewpoint
        Orient every normal towards this point (e.g. the sensor origin, same frame);
        when ``None`` normals point towards +z (horizontal ones keep their sign).
    tree
        A KD-tree over ``points`` to reuse.
    return_planarity
        Also return the surface variation ``l0 / (l0 + l1 + l2)`` per point (0 for a
        perfect plane, 1/3 for isotropic scatter).

    Returns
    -------
    numpy.ndarray or tuple
        ``(N, 3)`` unit normals (and the ``(N,)`` surface variation).
    """
    p = as_points(points)
    if len(p) < 3:
        raise InputError(f"need at least 3 points to estimate normals, got {len(p)}")
    k = int(min(max(k, 3), len(p)))
    tree = tree if tree is not None else cKDTree(p)
    normals = np.empty_like(p)
    variation = np.empty(len(p)) if return_planarity else None
    # In the tree's leaf order consecutive points are neighbours, so the searches and
    # gathers of a chunk stay in the cache (about twice as fast as the given order).
    order = tree.indices
    for start in range(0, len(p), NORMALS_CHUNK):
        rows = order[start : start + NORMALS_CHUNK]
        _, idx = tree.query(np.take(p, rows, axis=0), k=k, workers=-1)
        nb = np.take(p, idx, axis=0)
        nb -= (np.einsum("nkd->nd", nb) / k)[:, None, :]
        cov = np.matmul(nb.transpose(0, 2, 1), nb) / k
        evals, normals[rows] = _smallest_eigenvectors(cov)
        if variation is not None:
            total = evals.sum(axis=1)
            variation[rows] = np.where(
                total > 0, evals[:, 0] / np.where(total > 0, total, 1.0), 0.0
            )
    if viewpoint is not None:
        toward = np.asarray(viewpoint, dtype=float).reshape(1, 3) - p
    else:
        toward = np.broadcast_to(np.array([0.0, 0.0, 1.0]), p.shape)
    flip = np.einsum("ij,ij->i", normals, toward) < 0
    normals[flip] *= -1.0
    if variation is not None:
        return normals, variation
    return normals


def radius_mask(points: ArrayLike, center: ArrayLike, radius: float) -> NDArray[np.bool_]:
    """Boolean mask of the points within ``radius`` (metres) of ``center``."""
    p = as_points(points)
    d2 = np.sum((p - np.asarray(center, dtype=float).reshape(1, 3)) ** 2, axis=1)
    return d2 <= radius * radius


def crop_radius(points: ArrayLike, center: ArrayLike, radius: float) -> FloatArray:
    """The points within ``radius`` (metres) of ``center`` (a sphere crop)."""
    p = as_points(points)
    return p[radius_mask(p, center, radius)]


def box_mask(points: ArrayLike, lower: ArrayLike, upper: ArrayLike) -> NDArray[np.bool_]:
    """Boolean mask of the points inside the axis-aligned box ``[lower, upper]``."""
    p = as_points(points)
    lo = np.asarray(lower, dtype=float).reshape(1, 3)
    hi = np.asarray(upper, dtype=float).reshape(1, 3)
    return np.all((p >= lo) & (p <= hi), axis=1)


def crop_box(points: ArrayLike, lower: ArrayLike, upper: ArrayLike) -> FloatArray:
    """The points inside the axis-aligned box ``[lower, upper]`` (metres)."""
    p = as_points(points)
    return p[box_mask(p, lower, upper)]


def remove_statistical_outliers(
    points: ArrayLike, k: int = 20, std_ratio: float = 2.0
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Drop points whose mean distance to their neighbours is unusually large.

    A point is kept when its mean distance to its ``k`` nearest neighbours is at
    most ``mean + std_ratio * std`` of that figure over the whole cloud.

    Returns
    -------
    points, mask
        The kept points and the boolean mask of kept points.
    """
    p = as_points(points)
    if len(p) <= k:
        return p.copy(), np.ones(len(p), dtype=bool)
    d, _ = cKDTree(p).query(p, k=k + 1, workers=-1)
    mean_d = d[:, 1:].mean(axis=1)
    keep = mean_d <= mean_d.mean() + std_ratio * mean_d.std()
    return p[keep], keep
