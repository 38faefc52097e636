"""Segment-based global registration of an external map (paper 002, section 4.4).

Aligns a source map (e.g. a drone reconstruction, any frame) to the target map
the robot localizes in (LiDAR map, world frame) without an initial pose:

1. both maps are segmented (:func:`fabflow.positioning.segmentation.segment_map`):
   ground removed, Euclidean clusters, planar clusters dropped;
2. keypoints: the segment points on a ``keypoint_voxel`` grid;
3. descriptors: Fast Point Feature Histograms (FPFH, 33 bins, as in PCL/Open3D)
   over ``descriptor_radius``;
4. matching: mutual nearest neighbours in descriptor space (kd-tree);
5. geometric verification: both maps are levelled on their RANSAC ground planes;
   RANSAC hypotheses (heading + translation) come from pairs of correspondences
   whose horizontal and vertical separations agree; the ``n_candidates`` (``b``) most
   voted mutually distinct transformations, and the hypotheses from pairs of
   segment centroids with consistent separations, move the source segment
   centroids onto the target centroids;
   the candidate with most centroid matches within ``d_match`` wins (ties: the
   smallest largest match distance);
6. refinement: point-to-plane ICP of the matched source segments against the
   matched target segments; the registration is accepted only when the ICP RMSE over the
   matched segments is below ``max_rmse`` (``e*_icp``).

Paper 002 uses ISS keypoints and SHOT descriptors on stones (radii of 6 and
10 cm); at site scale (barracks, bridges, containers) this module uses voxel
keypoints and FPFH with radii in decimetres. ``b`` = 10, ``d_match`` = 1 m and
``e*_icp`` = 3 cm are Table 3's values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from fabflow.errors import LocalizationError
from fabflow.positioning.icp import icp, prepare_target
from fabflow.positioning.pointcloud import as_points, estimate_normals, voxel_downsample
from fabflow.positioning.segmentation import Segmentation, SegmentationParams, segment_map
from fabflow.transforms.se3 import apply_T, inv_T
from fabflow.transforms.so3 import exp_so3

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RegistrationParams:
    """Parameters of the global registration (Table 3 of paper 002 where it gives them).

    Attributes
    ----------
    keypoint_voxel
        Keypoint grid on the segment points (metres).
    normal_k
        Neighbours for the normals (estimated on the dense segment points and
        averaged per keypoint voxel).
    descriptor_radius
        FPFH support radius (metres).
    descriptor_k
        At most this many neighbours inside the radius.
    ransac_hypotheses
        Three-correspondence hypotheses drawn.
    inlier_distance
        A keypoint correspondence supports a hypothesis within this distance (metres).
    min_baseline
        The two keypoints of a hypothesis must be at least this far apart
        horizontally (metres), so that they fix the heading.
    n_candidates
        ``b``: most voted transformations that go on to centroid verification.
    d_match
        Largest distance between matched segment centroids (metres).
    max_rmse
        ``e*_icp``: largest accepted ICP RMSE over the matched segments (metres).
    min_centroid_matches
        The chosen candidate must match at least this many segment centroids (or
        all source segments when there are fewer).
    """

    keypoint_voxel: float = 0.2
    normal_k: int = 20
    descriptor_radius: float = 0.8
    descriptor_k: int = 40
    ransac_hypotheses: int = 4000
    inlier_distance: float = 0.3
    min_baseline: float = 1.0
    n_candidates: int = 10
    d_match: float = 1.0
    max_rmse: float = 0.03
    min_centroid_matches: int = 3


@dataclass(frozen=True, eq=False)
class GlobalRegistration:
    """The result of :func:`register_maps`.

    Attributes
    ----------
    T_target_source
        4x4 transform mapping source points into the target (map) frame.
    T_coarse
        The verified transformation before ICP refinement.
    rmse
        ICP RMSE over the matched segments (metres).
    fitness
        ICP fitness of the matched segments.
    n_correspondences
        Mutual descriptor matches.
    n_centroid_matches
        Segment centroids matched by the chosen candidate.
    matches
        ``(k, 2)`` pairs ``(source segment id, target segment id)``.
    source, target
        The segmentations of both maps (their object tables).
    covariance
        6x6 covariance of ``T_target_source`` from the ICP refinement.
    """

    T_target_source: FloatArray
    T_coarse: FloatArray
    rmse: float
    fitness: float
    n_correspondences: int
    n_centroid_matches: int
    matches: NDArray[np.int64]
    source: Segmentation
    target: Segmentation
    covariance: FloatArray


REGISTRATION_SEGMENTATION = SegmentationParams(cluster_distance=0.25)
"""Segmentation for registration: Table 3, with clusters grown over 25 cm gaps so that
sparsely sampled objects stay whole."""


def fpfh(
    points: ArrayLike, normals: ArrayLike, radius: float, k: int = 60, tree: cKDTree | None = None
) -> FloatArray:
    """Fast Point Feature Histograms (Rusu et al. 2009), 33 bins per point.

    Follows PCL/Open3D: per point, the simplified histogram (SPFH) of the pair
    features ``(theta, alpha, phi)`` to its neighbours within ``radius`` (11 bins
    each, in percent), then FPFH = SPFH + the neighbours' SPFH weighted by
    inverse distance (normalized per feature group).

    Parameters
    ----------
    points, normals
        ``(N, 3)`` points (metres) and unit normals.
    radius
        Support radius (metres).
    k
        Largest number of neighbours considered.
    tree
        KD-tree over ``points`` to reuse.

    Returns
    -------
    numpy.ndarray
        ``(N, 33)`` descriptors.
    """
    p = as_points(points)
    n = np.ascontiguousarray(normals, dtype=float)
    tree = tree if tree is not None else cKDTree(p)
    kk = int(min(k + 1, len(p)))
    dist, idx = tree.query(p, k=kk, distance_upper_bound=radius, workers=-1)
    dist, idx = dist[:, 1:], idx[:, 1:]
    valid = np.isfinite(dist) & (dist > 0)
    idx = np.where(valid, idx, 0)
    d = p[idx] - p[:, None, :]
    f4 = np.where(valid, dist, 1.0)
    dn = d / f4[..., None]
    n1 = np.broadcast_to(n[:, None, :], d.shape)
    n2 = n[idx]
    a1 = np.einsum("nki,nki->nk", n1, dn)
    a2 = np.einsum("nki,nki->nk", n2, dn)
    # which point is the pair's source (PCL's rule); near-ties (equal normals) keep the
    # order, so that rounding cannot decide
    swap = np.arccos(np.clip(np.abs(a1), 0, 1)) > np.arccos(np.clip(np.abs(a2), 0, 1)) + 1e-9
    s1 = np.where(swap[..., None], n2, n1)
    s2 = np.where(swap[..., None], n1, n2)
    dn = np.where(swap[..., None], -dn, dn)
    f3 = np.where(swap, -a2, a1)
    v = np.cross(dn, s1)
    vn = np.linalg.norm(v, axis=-1)
    valid &= vn > 1e-12
    v = v / np.where(vn > 1e-12, vn, 1.0)[..., None]
    w = np.cross(s1, v)
    f2 = np.einsum("nki,nki->nk", v, s2)
    f1 = np.arctan2(np.einsum("nki,nki->nk", w, s2), np.einsum("nki,nki->nk", s1, s2))
    bins = np.stack(
        [
            np.floor(11 * (f1 + np.pi) / (2 * np.pi)),
            11 + np.floor(11 * (f2 + 1) * 0.5),
            22 + np.floor(11 * (f3 + 1) * 0.5),
        ],
        axis=-1,
    )
    bins = np.clip(bins, [0, 11, 22], [10, 21, 32]).astype(np.int64)
    count = valid.sum(axis=1)
    incr = np.where(count > 0, 100.0 / np.maximum(count, 1), 0.0)
    flat = (np.arange(len(p))[:, None, None] * 33 + bins).ravel()
    weights = np.broadcast_to((valid * incr[:, None])[..., None], bins.shape).ravel()
    spfh = np.bincount(flat, weights=weights, minlength=33 * len(p)).reshape(len(p), 33)
    inv = np.where(valid, 1.0 / (f4 * f4), 0.0)  # PCL/Open3D weight by squared distance
    neigh = np.einsum("nk,nkj->nj", inv, spfh[idx])
    sums = neigh.reshape(len(p), 3, 11).sum(axis=2)
    scale = np.where(sums > 0, 100.0 / np.where(sums > 0, sums, 1.0), 0.0)
    neigh = (neigh.reshape(len(p), 3, 11) * scale[:, :, None]).reshape(len(p), 33)
    return spfh + neigh


def _centroid_pair_hypotheses(
    cs: FloatArray, ct: FloatArray, params: RegistrationParams
) -> FloatArray:
    """Heading + translation hypotheses from pairs of levelled segment centroids.

    Every source pair ``(i, j)`` is tried against every target pair ``(k, l)`` whose
    horizontal and vertical separations agree within ``d_match / 2``.
    """
    ns, nt = len(cs), len(ct)
    if ns < 2 or nt < 2:
        return np.zeros((0, 4, 4))
    si, sj = np.triu_indices(ns, 1)
    tk, tl = np.nonzero(~np.eye(nt, dtype=bool))
    ds = (cs[sj] - cs[si])[:, None, :]
    dt = (ct[tl] - ct[tk])[None, :, :]
    hs, ht = np.linalg.norm(ds[..., :2], axis=2), np.linalg.norm(dt[..., :2], axis=2)
    ok = (
        (np.abs(hs - ht) < params.d_match / 2)
        & (np.abs(ds[..., 2] - dt[..., 2]) < params.d_match / 2)
        & (np.minimum(hs, ht) > params.min_baseline)
    )
    a, b = np.nonzero(ok)
    if len(a) == 0:
        return np.zeros((0, 4, 4))
    d_s, d_t = ds[a, 0], dt[0, b]
    yaw = np.arctan2(d_t[:, 1], d_t[:, 0]) - np.arctan2(d_s[:, 1], d_s[:, 0])
    c, sn = np.cos(yaw), np.sin(yaw)
    H = np.tile(np.eye(4), (len(a), 1, 1))
    H[:, 0, 0], H[:, 0, 1], H[:, 1, 0], H[:, 1, 1] = c, -sn, sn, c
    mid_s = 0.5 * (cs[si[a]] + cs[sj[a]])
    mid_t = 0.5 * (ct[tk[b]] + ct[tl[b]])
    H[:, :3, 3] = mid_t - np.einsum("kij,kj->ki", H[:, :3, :3], mid_s)
    return H


def _distinct_candidates(
    hyps: FloatArray, votes: NDArray[np.int64], b: int, distance: float
) -> list[int]:
    """The ``b`` most voted hypotheses that differ from each other (non-maximum suppression).

    Repetitive structure (a row of columns) makes many near-identical wrong
    hypotheses collect the most votes; keeping one per cluster of similar
    transformations lets the right one reach centroid verification. Two hypotheses
    are similar when they move the source origin's neighbourhood (a 10 m lever) by
    less than ``distance``.
    """
    chosen: list[int] = []
    for h in np.argsort(-votes, kind="stable"):
        if votes[h] == 0 or len(chosen) == b:
            break
        similar = False
        for c in chosen:
            dt = np.linalg.norm(hyps[h, :3, 3] - hyps[c, :3, 3])
            cos = (np.trace(hyps[h, :3, :3].T @ hyps[c, :3, :3]) - 1.0) / 2.0
            angle = float(np.arccos(np.clip(cos, -1.0, 1.0)))
            if dt + 10.0 * angle < distance:
                similar = True
                break
        if not similar:
            chosen.append(int(h))
    return chosen


def _level(plane: FloatArray) -> FloatArray:
    """``T_level_map``: rotates the plane normal onto +z and moves the plane to z = 0."""
    n = np.asarray(plane[:3], dtype=float)
    if np.linalg.norm(n) < 0.5:
        return np.eye(4)
    axis = np.cross(n, [0.0, 0.0, 1.0])
    angle = np.arctan2(np.linalg.norm(axis), n[2])
    rot = axis / np.linalg.norm(axis) * angle if np.linalg.norm(axis) > 1e-12 else np.zeros(3)
    T = np.eye(4)
    T[:3, :3] = exp_so3(rot)
    T[2, 3] = plane[3]  # a point p on the plane has n.p = -d, so z' = n.p + d = 0
    return T


def _keypoints(seg: Segmentation, params: RegistrationParams) -> tuple[FloatArray, FloatArray]:
    """Voxel keypoints of the segment points, with normals estimated on the dense points."""
    pts = np.vstack([s.points for s in seg.segments]) if seg.segments else np.zeros((0, 3))
    if len(pts) < 10:
        raise LocalizationError(
            f"global registration needs non-planar segments; found {len(seg.segments)}"
        )
    nrm = estimate_normals(pts, k=params.normal_k)
    kp, kn = voxel_downsample(pts, params.keypoint_voxel, nrm)  # type: ignore[arg-type]
    assert kn is not None
    return kp, kn


def register_maps(
    source: ArrayLike,
    target: ArrayLike,
    rng: np.random.Generator,
    params: RegistrationParams = RegistrationParams(),
    segmentation: SegmentationParams = REGISTRATION_SEGMENTATION,
    target_segmentation: Segmentation | None = None,
) -> GlobalRegistration:
    """Align a source map to the target map without an initial pose.

    Parameters
    ----------
    source
        ``(N, 3)`` external map (metres, its own frame; z roughly up for the ground
        removal).
    target
        ``(M, 3)`` the robot's map (metres, world frame, z up).
    rng
        Draws the RANSAC hypotheses.
    params, segmentation
        Registration and segmentation parameters.
    target_segmentation
        A segmentation of ``target`` to reuse (it is computed otherwise).

    Raises
    ------
    LocalizationError
        Too few segments or matches, no candidate matching at least two segment
        centroids, or an ICP RMSE above ``params.max_rmse``.
    """
    tgt_pts = as_points(target, "target map")
    src_seg = segment_map(source, rng, segmentation)
    tgt_seg = target_segmentation or segment_map(tgt_pts, rng, segmentation)
    ks, ns = _keypoints(src_seg, params)
    kt, nt = _keypoints(tgt_seg, params)
    fs = fpfh(ks, ns, params.descriptor_radius, params.descriptor_k)
    ft = fpfh(kt, nt, params.descriptor_radius, params.descriptor_k)
    _, st = cKDTree(ft).query(fs, k=1, workers=-1)
    _, ts = cKDTree(fs).query(ft, k=1, workers=-1)
    mutual = ts[st] == np.arange(len(fs))
    corr = np.column_stack([np.flatnonzero(mutual), st[mutual]])
    if len(corr) < 3:
        raise LocalizationError(f"only {len(corr)} mutual descriptor matches between the maps")
    S, Q = ks[corr[:, 0]], kt[corr[:, 1]]

    # Both maps are levelled on their ground planes, so a hypothesis is a heading and a
    # translation (4 DOF) from two correspondences: far likelier to be outlier-free
    # than a three-point sample when most descriptor matches are wrong.
    L_s, L_t = _level(src_seg.ground_plane), _level(tgt_seg.ground_plane)
    Sl, Ql = apply_T(L_s, S), apply_T(L_t, Q)
    pick = rng.integers(0, len(corr), (params.ransac_hypotheses, 2))
    ds = Sl[pick[:, 1]] - Sl[pick[:, 0]]
    dq = Ql[pick[:, 1]] - Ql[pick[:, 0]]
    hs, hq = np.linalg.norm(ds[:, :2], axis=1), np.linalg.norm(dq[:, :2], axis=1)
    good = (
        (np.abs(hs - hq) < params.inlier_distance)
        & (np.abs(ds[:, 2] - dq[:, 2]) < params.inlier_distance)
        & (np.minimum(hs, hq) > params.min_baseline)
    )
    if not good.any():
        raise LocalizationError("no geometrically consistent pair of descriptor matches")
    yaw = np.arctan2(dq[good, 1], dq[good, 0]) - np.arctan2(ds[good, 1], ds[good, 0])
    c, sn = np.cos(yaw), np.sin(yaw)
    hyps = np.tile(np.eye(4), (len(yaw), 1, 1))
    hyps[:, 0, 0], hyps[:, 0, 1], hyps[:, 1, 0], hyps[:, 1, 1] = c, -sn, sn, c
    mid_s = 0.5 * (Sl[pick[good, 0]] + Sl[pick[good, 1]])
    mid_q = 0.5 * (Ql[pick[good, 0]] + Ql[pick[good, 1]])
    hyps[:, :3, 3] = mid_q - np.einsum("kij,kj->ki", hyps[:, :3, :3], mid_s)
    hyps = np.einsum("ij,kjl,lm->kim", inv_T(L_t), hyps, L_s)
    votes = np.zeros(len(hyps), dtype=np.int64)
    for start in range(0, len(hyps), 256):
        H = hyps[start : start + 256]
        moved = np.einsum("kij,mj->kmi", H[:, :3, :3], S) + H[:, None, :3, 3]
        votes[start : start + 256] = (
            np.linalg.norm(moved - Q[None], axis=2) < params.inlier_distance
        ).sum(axis=1)
    order = _distinct_candidates(hyps, votes, params.n_candidates, params.d_match)

    cs, ct = src_seg.centroids, tgt_seg.centroids
    # keypoint matches between partial LiDAR views and complete external maps are
    # mostly wrong, so candidates also come from pairs of segment centroids
    pair_hyps = _centroid_pair_hypotheses(apply_T(L_s, cs), apply_T(L_t, ct), params)
    if len(pair_hyps):
        pair_hyps = np.einsum("ij,kjl,lm->kim", inv_T(L_t), pair_hyps, L_s)
        order = order + list(range(len(hyps), len(hyps) + len(pair_hyps)))
        hyps = np.concatenate([hyps, pair_hyps])
    ct_tree = cKDTree(ct)
    best: tuple[int, float, int, NDArray[np.int64]] | None = None
    for h in order:
        dist, j = ct_tree.query(apply_T(hyps[h], cs), k=1)
        ok = dist <= params.d_match
        n_ok, worst = int(ok.sum()), float(dist[ok].max()) if ok.any() else np.inf
        if best is None or n_ok > best[0] or (n_ok == best[0] and worst < best[1]):
            best = (n_ok, worst, int(h), np.column_stack([np.flatnonzero(ok), j[ok]]))
    assert best is not None
    n_match, _, h, matches = best
    if n_match < min(params.min_centroid_matches, len(cs)):
        raise LocalizationError(
            f"the best candidate matches only {n_match} segment centroid(s) within "
            f"{params.d_match:g} m"
        )
    T_coarse = hyps[h]
    matched_src = np.vstack([src_seg.segments[i].points for i in matches[:, 0]])
    matched_tgt = np.vstack([tgt_seg.segments[j].points for j in np.unique(matches[:, 1])])
    res = icp(
        voxel_downsample(matched_src, 2 * segmentation.voxel_size)[0],
        prepare_target(matched_tgt),
        init=T_coarse,
        max_correspondence_distance=(0.4, 0.15, 0.05),
        kernel="huber",
        min_step=1e-4,
    )
    if res.inlier_rmse > params.max_rmse:
        raise LocalizationError(
            f"global registration rejected: ICP RMSE {1e3 * res.inlier_rmse:.1f} mm over the "
            f"matched segments exceeds {1e3 * params.max_rmse:.1f} mm"
        )
    return GlobalRegistration(
        T_target_source=res.T,
        T_coarse=T_coarse,
        rmse=res.inlier_rmse,
        fitness=res.fitness,
        n_correspondences=len(corr),
        n_centroid_matches=n_match,
        matches=matches,
        source=src_seg,
        target=tgt_seg,
        covariance=res.covariance,
    )
