"""The map a LiDAR scan is localized in: points, normals and search trees.

A map is read from a file (:func:`load_map`), made from a world-frame cloud
(:func:`map_from_points`), or built offline from several scans of the site
(:func:`build_map`: each new scan is aligned by ICP to the map merged so far,
starting from its odometry guess; the first scan anchors the map frame). Besides
its points a :class:`ScanMap` carries what is known of its errors, which every
fix in it counts (:func:`fabflow.positioning.scan_matching.localize_scan`): the
drift of the scans it was built from, the blocks added at their design poses,
and the range bias of the channels that measured its points.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.positioning.icp import IcpTarget, icp, prepare_target
from fabflow.positioning.pointcloud import as_points, voxel_downsample
from fabflow.positioning.pointcloud_io import read_point_cloud
from fabflow.transforms.se3 import apply_T

FloatArray = NDArray[np.float64]

MAP_NORMAL_K = 20
"""Neighbours of the PCA normals of a map without normals. Fewer are faster but
noisier: on the simulated site's 3 cm map from noisy scans, 10 neighbours put the
normals 3.3 deg off the surfaces (median; 1.4 deg with 20) and the localization
0.81 mm off instead of 0.73 (median over 30 stations)."""
COVARIANCE_BLOCK = 1.0
"""Edge (m) of the cubes of scan points whose residual errors the covariance treats
as shared: the scale of the surfaces of a site (a column, a pallet, a stretch of
wall or railing). Errors that do not average over the points of one surface (the
map's error there, voxel-centroid bias along edges, facets and noisy grazing
returns) correlate residuals metres apart; see docs/icp.md for the measurement."""


@dataclass(frozen=True, eq=False)
class ScanMap:
    """A point-cloud map in the world frame, ready for repeated localization.

    Attributes
    ----------
    target
        Map points, normals and KD-tree (world frame, metres).
    coarse
        The same map on a 4x coarser voxel grid, for the coarse ICP stage (nearest
        neighbour searches far from the surface are much cheaper on it).
    voxel_size
        Voxel grid the map was downsampled on (metres).
    T_world_scans
        Poses of the scans the map was built from (empty for a map read from file).
    map_covariance
        6x6 covariance (fabflow's pose error, world frame) of where the map's
        scans lie off their true poses, averaged over the scans: each scan's is
        its registration's covariance plus the average of those placed before it
        (:func:`build_map`; on the simulated site it predicts the scans' drift
        within 0.6-1.05 of its RMS). Added as it is to the covariance of every
        scan localized in the map: each scan's error is about its own origin and
        is not carried to the fix's (an approximation). ``None`` for a map taken
        as exact (read from file, or built from known poses).
    point_groups, group_sigma
        ``(M,)`` the block each point of ``target`` was sampled from where blocks
        were added at their design poses (``-1``: none), and those blocks'
        placement error per axis (metres): the fix's covariance counts it
        (:func:`~fabflow.positioning.icp.icp`'s ``target_groups``).
    ray_groups, ray_directions, ray_sigma
        ``(M,)`` the laser channel of the mapping run that measured each point of
        ``target`` (``-1``: none, e.g. an added block), ``(M, 3)`` the unit
        direction (world) it was measured along, and the channels' range bias over
        that run (metres): the fix's covariance counts it (``icp``'s ``map_rays``).
        Known for the simulated site map built from known poses
        (:func:`fabflow.sensors.site_map.simulated_site_map`).
    """

    target: IcpTarget
    coarse: IcpTarget
    voxel_size: float
    T_world_scans: tuple[FloatArray, ...] = ()
    map_covariance: FloatArray | None = None
    point_groups: NDArray[np.intp] | None = None
    group_sigma: float = 0.0
    ray_groups: NDArray[np.intp] | None = None
    ray_directions: FloatArray | None = None
    ray_sigma: float = 0.0

    @property
    def map_rays(self) -> tuple[NDArray[np.intp], FloatArray, float] | None:
        """``icp``'s ``map_rays`` of this map, or ``None`` when it has none."""
        if self.ray_groups is None or self.ray_directions is None or self.ray_sigma == 0:
            return None
        return self.ray_groups, self.ray_directions, self.ray_sigma

    @property
    def points(self) -> FloatArray:
        """``(M, 3)`` map points (world frame, metres)."""
        return self.target.points

    @property
    def normals(self) -> FloatArray:
        """``(M, 3)`` map normals."""
        assert self.target.normals is not None
        return self.target.normals

    def __len__(self) -> int:
        return len(self.target)


def map_from_points(
    points: ArrayLike, voxel_size: float = 0.03, normals: ArrayLike | None = None
) -> ScanMap:
    """Voxelize a world-frame cloud and estimate its normals unless given."""
    p, n = voxel_downsample(points, voxel_size, normals)
    if len(p) < 100:
        raise InputError(f"a map needs at least 100 points after voxelizing, has {len(p)}")
    target = prepare_target(p, n, normal_k=MAP_NORMAL_K)  # one KD-tree for normals and ICP
    pc, nc = voxel_downsample(p, 4 * voxel_size, target.normals)
    return ScanMap(
        target=target,
        coarse=prepare_target(pc, nc) if len(pc) >= 100 else target,
        voxel_size=voxel_size,
    )


def transform_map(scan_map: ScanMap, T: ArrayLike) -> ScanMap:
    """The map moved by the rigid motion ``T`` (4x4): points, normals and trees.

    For a map surveyed in another frame (``T`` = the pose of that frame in the
    world), or to study a map that is off.
    """
    T = np.asarray(T, dtype=float)

    def moved(target: IcpTarget) -> IcpTarget:
        normals = None if target.normals is None else target.normals @ T[:3, :3].T
        return prepare_target(apply_T(T, target.points), normals)

    C = scan_map.map_covariance
    if C is not None:  # turned with the map (both its translation and rotation parts)
        R6 = np.kron(np.eye(2), T[:3, :3])
        C = R6 @ C @ R6.T
    return ScanMap(
        target=moved(scan_map.target),
        coarse=moved(scan_map.coarse),
        voxel_size=scan_map.voxel_size,
        T_world_scans=tuple(T @ np.asarray(P) for P in scan_map.T_world_scans),
        map_covariance=C,
        point_groups=scan_map.point_groups,
        group_sigma=scan_map.group_sigma,
        ray_groups=scan_map.ray_groups,
        ray_directions=None
        if scan_map.ray_directions is None
        else scan_map.ray_directions @ T[:3, :3].T,
        ray_sigma=scan_map.ray_sigma,
    )


def load_map(path: str | Path, voxel_size: float = 0.03) -> ScanMap:
    """Read a map file (PLY, XYZ, CSV; world frame, metres) and prepare it.

    Normals stored in a PLY file (``nx, ny, nz``) are used; otherwise they are
    estimated by PCA over 20 neighbours.

    Raises
    ------
    InputError
        The file is unreadable or holds too few points.
    """
    cloud = read_point_cloud(path)
    try:
        return map_from_points(cloud.points, voxel_size, cloud.normals)
    except InputError as exc:
        raise InputError(exc.message, source=path) from None


def build_map(
    scans: Sequence[ArrayLike],
    T_world_scan_guess: Sequence[ArrayLike],
    voxel_size: float = 0.03,
    register: bool = True,
    normals: Sequence[ArrayLike] | None = None,
) -> ScanMap:
    """Register scans into one map, merge and voxelize them (offline mapping).

    Parameters
    ----------
    scans
        Point clouds, each in its sensor frame (metres).
    T_world_scan_guess
        A 4x4 pose guess per scan (odometry). The first is taken as exact: it
        anchors the map in the world frame.
    voxel_size
        Voxel grid of the map (metres; 3 cm in paper 002, Table 3).
    register
        Refine every scan after the first by ICP against the map built so far;
        ``False`` trusts the guesses (known sensor poses).
    normals
        Unit normals of every scan's points in its sensor frame (e.g. a
        simulation's exact ones), turned with the scan as it is placed; ``None``:
        estimated from the merged map (20 neighbours).

    Returns
    -------
    ScanMap
        The map with the refined scan poses.
    """
    if len(scans) == 0 or len(scans) != len(T_world_scan_guess):
        raise InputError("build_map needs one pose guess per scan and at least one scan")
    if normals is not None and len(normals) != len(scans):
        raise InputError("build_map needs normals for every scan, or none")
    poses: list[FloatArray] = []
    merged = np.zeros((0, 3))
    turned = None if normals is None else np.zeros((0, 3))
    # each scan is registered to the map of all before it, so it inherits their average
    # error (taken as fully shared) on top of its own registration's
    placed_cov = [np.zeros((6, 6))]
    for i, (scan, guess) in enumerate(zip(scans, T_world_scan_guess, strict=True)):
        s = as_points(scan, f"scan {i}")
        T = np.asarray(guess, dtype=float).reshape(4, 4)
        if i > 0 and register:
            target = prepare_target(*voxel_downsample(merged, voxel_size, turned))
            src = voxel_downsample(s, 2 * voxel_size)[0]
            res = icp(
                src,
                target,
                init=T,
                max_correspondence_distance=(0.5, 0.2, 0.08),
                covariance_block=COVARIANCE_BLOCK,
            )
            T = res.T
            placed_cov.append(res.covariance + np.mean(placed_cov, axis=0))
        poses.append(T)
        merged = np.vstack([merged, apply_T(T, s)])
        if turned is not None and normals is not None:
            turned = np.vstack([turned, np.asarray(normals[i], dtype=float) @ T[:3, :3].T])
    result = map_from_points(merged, voxel_size, turned)
    return ScanMap(
        target=result.target,
        coarse=result.coarse,
        voxel_size=voxel_size,
        T_world_scans=tuple(poses),
        map_covariance=np.mean(placed_cov, axis=0) if register and len(scans) > 1 else None,
    )
