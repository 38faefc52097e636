"""A simulated LiDAR map of the site, and the as-built structure added to a map.

:func:`simulated_site_map` scans the simulated site (:mod:`fabflow.sensors.site_scene`)
from a ring of poses before construction starts, as an offline mapping run
would; :func:`with_as_built` adds the blocks built so far at their design poses.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from fabflow.design.elements import Element, element_boxes
from fabflow.positioning.scan_map import FloatArray, ScanMap, build_map, map_from_points
from fabflow.sensors.lidar import HESAI_QT64, LidarModel, simulate_scan
from fabflow.sensors.lidar_errors import NO_ERRORS, LidarErrorModel, draw_channel_bias
from fabflow.sensors.site_scene import boxes_mesh, site_scene
from fabflow.transforms.se3 import apply_T, perturb


def mapping_poses(center: Sequence[float] = (2.0, 1.65), height: float = 1.8) -> FloatArray:
    """Sensor poses of the simulated offline mapping run: a ring around ``center``."""
    angles = np.radians(np.arange(0, 360, 45))
    poses = np.tile(np.eye(4), (len(angles) + 1, 1, 1))
    poses[0, :3, 3] = [center[0], center[1] - 4.5, height]
    for i, a in enumerate(angles, start=1):
        c, s = np.cos(a), np.sin(a)
        poses[i, :3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        poses[i, :3, 3] = [center[0] + 5.0 * c, center[1] + 5.0 * s, height]
    return poses


@functools.lru_cache(maxsize=4)
def simulated_site_map(
    obstacles: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (),
    voxel_size: float = 0.03,
    seed: int = 0,
    model: LidarModel | None = None,
    prisms: tuple[tuple[tuple[tuple[float, float], ...], float, float], ...] = (),
    errors: LidarErrorModel = NO_ERRORS,
    registered: bool = False,
) -> ScanMap:
    """A map of the simulated site built from nine simulated scans (cached).

    The scans are taken on a ring around the cabin before construction starts, so
    the map holds the ground, the landmarks and the given box obstacles, but no
    blocks. The normals are those of the scene triangles hit (as a SLAM map with
    surface normals would carry), which saves the PCA over 160k points.

    Parameters
    ----------
    obstacles
        Box obstacles ``((lower), (upper))`` of the site (metres).
    voxel_size
        Map voxel grid (metres).
    seed
        Seed of the range errors of the mapping scans.
    model
        The mapping LiDAR (default: the Hesai QT64 model).
    prisms
        Polygon obstacles ``(plan polygon, z_min, z_max)`` of the site (metres).
    errors
        Range errors of the mapping scans (one run: one channel bias for all).
    registered
        ``False``: the scans are placed at their true poses (a perfect offline
        SLAM). ``True``: as a mapping run places them
        (:func:`~fabflow.positioning.scan_map.build_map`), each registered
        to the map of the scans before it from its true pose off by
        :data:`ODOMETRY_ERROR` (the odometry), the first at its true pose (the
        map's tie to the site survey): the map drifts by what each registration
        errs.
    """

    rng = np.random.default_rng(seed)
    scene = site_scene(obstacles=obstacles, prisms=prisms)
    model = model or HESAI_QT64
    poses = mapping_poses()
    bias = draw_channel_bias(errors, model.n_beams, rng)
    scans = [simulate_scan(scene, T, rng, model, errors, bias) for T in poses]
    if registered:
        # as a mapping run places them: from the odometry, then registered
        err = np.zeros((len(poses), 6))
        err[:, :3] = rng.normal(0.0, ODOMETRY_ERROR[0], (len(poses), 3))
        err[:, 5] = rng.normal(0.0, np.radians(ODOMETRY_ERROR[1]), len(poses))
        guesses = [poses[0], *(perturb(T, e) for T, e in zip(poses[1:], err[1:], strict=True))]
        normals_lidar = [
            scene.face_normals[s.face_index] @ T[:3, :3] for s, T in zip(scans, poses, strict=True)
        ]
        return build_map([s.points for s in scans], guesses, voxel_size, True, normals_lidar)
    points = np.vstack([apply_T(s.T_world_lidar, s.points) for s in scans])
    normals = np.vstack([scene.face_normals[s.face_index] for s in scans])
    result = map_from_points(points, voxel_size, normals)
    channels, rays = None, None
    if errors.channel_bias_sigma > 0:
        # each map point (a voxel's centroid) errs as the scan point nearest it: along
        # that point's ray, by its channel's bias
        directions = model.directions()
        channel = np.concatenate([s.ray_index // model.n_columns for s in scans])
        ray = np.vstack([directions[s.ray_index] @ s.T_world_lidar[:3, :3].T for s in scans])
        nearest = cKDTree(points).query(result.target.points)[1]
        channels, rays = channel[nearest].astype(np.intp), ray[nearest]
    return ScanMap(
        target=result.target,
        coarse=result.coarse,
        voxel_size=voxel_size,
        T_world_scans=tuple(poses),
        ray_groups=channels,
        ray_directions=rays,
        ray_sigma=errors.channel_bias_sigma if channels is not None else 0.0,
    )


ODOMETRY_ERROR = (0.03, 1.0)
"""Pose guess error of a mapping scan: (metres per axis, degrees of heading)."""


def with_as_built(
    scan_map: ScanMap,
    built: Sequence[Element],
    rng: np.random.Generator,
    placement_sigma: float = 0.0,
) -> ScanMap:
    """The map plus the surfaces of the blocks built so far, at their design poses.

    From inside a growing structure most of a scan sees new blocks, which the site
    map does not hold; adding them (sampled on the map's voxel grid, with their
    face normals) keeps the fitness up and removes the pull of unmatched block
    points on nearby map surfaces. The blocks stand where the design puts them,
    the real ones where they were placed: with ``placement_sigma`` (metres per
    axis) each map point is labelled with its block (the nearest sample within
    a voxel) and the fixes' covariance counts that error
    (``ScanMap.point_groups``).
    """

    T_boxes, extents = element_boxes(built)
    if not len(extents):
        return scan_map
    mesh = boxes_mesh(T_boxes, extents)
    n = int(np.ceil(mesh.area / scan_map.voxel_size**2))
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=int(rng.integers(2**31)))
    merged = map_from_points(
        np.vstack([scan_map.points, np.asarray(pts, dtype=float)]),
        scan_map.voxel_size,
        np.vstack([scan_map.normals, mesh.face_normals[face]]),
    )
    ray_groups, ray_directions = None, None
    if scan_map.ray_groups is not None and scan_map.ray_directions is not None:
        # the site's points keep the channel and ray of the map point they came from
        d, nearest = cKDTree(scan_map.points).query(
            merged.target.points, distance_upper_bound=scan_map.voxel_size / 2
        )
        found = np.isfinite(d)
        nearest = np.minimum(nearest, len(scan_map.points) - 1)
        ray_groups = np.where(found, scan_map.ray_groups[nearest], -1).astype(np.intp)
        ray_directions = np.where(found[:, None], scan_map.ray_directions[nearest], 0.0)
    groups = None
    if placement_sigma > 0:
        # boxes_mesh gives every box the same triangles, in order
        block = np.asarray(face) // (len(mesh.faces) // len(extents))
        d, nearest = cKDTree(pts).query(
            merged.target.points, distance_upper_bound=scan_map.voxel_size
        )
        groups = np.where(np.isfinite(d), block[np.minimum(nearest, len(block) - 1)], -1)
    return ScanMap(
        target=merged.target,
        coarse=merged.coarse,
        voxel_size=scan_map.voxel_size,
        T_world_scans=scan_map.T_world_scans,
        map_covariance=scan_map.map_covariance,
        point_groups=None if groups is None else groups.astype(np.intp),
        group_sigma=float(placement_sigma) if groups is not None else 0.0,
        ray_groups=ray_groups,
        ray_directions=ray_directions,
        ray_sigma=scan_map.ray_sigma if ray_groups is not None else 0.0,
    )
