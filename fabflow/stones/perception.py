"""From scans to the object database (paper 002, sections 4.2 to 4.5).

The machine's LiDAR scans are accumulated into a map on a 3 cm voxel grid and
segmented (ground removed by a RANSAC plane, Euclidean clusters, planar
clusters dropped; Table 3). With a drone reconstruction of the site (the
"vision" map, any frame), the segment-based global registration of
:mod:`fabflow.positioning.global_registration` aligns it with the LiDAR map;
the two maps merged are segmented again, and every segment becomes an object
of the database: the drone sees the tops and far sides the LiDAR misses, which
joins what the LiDAR saw of a stone in pieces. A registration that fails (its
ICP RMSE above ``e*_icp`` = 3 cm, or too few segment matches) leaves the LiDAR
segments as the objects. The map keeps what lies within ``R_map`` = 10 m
(horizontally) of the machine, Table 3's robot-centric local map.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import LocalizationError
from fabflow.manipulation.objects import ObjectDatabase, add_segments
from fabflow.positioning.global_registration import (
    GlobalRegistration,
    RegistrationParams,
    register_maps,
)
from fabflow.positioning.pointcloud import as_points, voxel_downsample
from fabflow.positioning.segmentation import Segmentation, SegmentationParams, segment_map
from fabflow.transforms.se3 import apply_T

FloatArray = NDArray[np.float64]

STONE_SEGMENTATION = SegmentationParams()
"""Segmentation of the stone site: Table 3 of paper 002 as it stands (3 cm voxels,
10 cm ground margin)."""

STONE_REGISTRATION = RegistrationParams(
    keypoint_voxel=0.1,
    descriptor_radius=0.3,
    inlier_distance=0.15,
    min_baseline=1.0,
)
"""Global registration at the scale of stones: keypoints every 10 cm and FPFH over
30 cm (the paper's ISS / SHOT radii are 6 and 10 cm), hypotheses from pairs of
matches at least 1 m apart; ``b``, ``d_match`` and ``e*_icp`` as Table 3."""


@dataclass(frozen=True, eq=False)
class Perception:
    """What the perception pipeline found.

    Attributes
    ----------
    map_points
        ``(N, 3)`` the LiDAR map on its voxel grid (metres, world).
    segmentation
        The LiDAR map's segmentation (ground plane, segments).
    objects
        The segmentation the objects come from: of the LiDAR map merged with the
        registered vision map when the registration succeeded, else the LiDAR
        map's.
    registration
        The vision map's registration to the LiDAR map, or ``None`` (no vision
        map, or rejected: see ``registration_error``).
    registration_error
        Why the registration was rejected, or ``None``.
    registration_time_s
        Wall time of the segment-based registration (both maps' segmentation,
        keypoints, descriptors, matching, verification, ICP; seconds), 0 without
        a vision map.
    db
        The object database: one object per segment of ``objects``.
    """

    map_points: FloatArray
    segmentation: Segmentation
    objects: Segmentation
    registration: GlobalRegistration | None
    registration_error: str | None
    registration_time_s: float
    db: ObjectDatabase

    @property
    def ground_plane(self) -> FloatArray:
        """``(4,)`` the ground plane ``(n, d)`` with ``n . p + d = 0``, ``n`` up."""
        plane = np.asarray(self.segmentation.ground_plane, dtype=float)
        return plane if plane[2] >= 0 else -plane


R_MAP = 10.0
"""``R_map`` (Table 3): radius of the robot-centric local map (metres, horizontal)."""


def lidar_map(
    scans_world: ArrayLike,
    center: ArrayLike | None = None,
    voxel_size: float = STONE_SEGMENTATION.voxel_size,
) -> FloatArray:
    """Accumulated scan points on the map's voxel grid (metres, world).

    With ``center`` (the machine's position, world) only the points within
    :data:`R_MAP` of it, horizontally, are kept.
    """
    pts = as_points(scans_world, "scan points")
    if center is not None:
        c = np.asarray(center, dtype=float)[:2]
        pts = pts[np.linalg.norm(pts[:, :2] - c, axis=1) <= R_MAP]
    return voxel_downsample(pts, voxel_size)[0]


def perceive(
    map_points: ArrayLike,
    rng: np.random.Generator,
    vision_points: ArrayLike | None = None,
    segmentation: SegmentationParams = STONE_SEGMENTATION,
    registration: RegistrationParams = STONE_REGISTRATION,
) -> Perception:
    """Segment the map, register the vision map to it, fill the object database.

    Parameters
    ----------
    map_points
        ``(N, 3)`` the LiDAR map (metres, world frame, z up).
    rng
        Draws the RANSAC hypotheses.
    vision_points
        ``(M, 3)`` a drone reconstruction (metres, its own frame, z roughly up), or
        ``None``.
    segmentation, registration
        Parameters (Table 3 of paper 002 where it gives them).
    """
    pts = lidar_map(map_points, voxel_size=segmentation.voxel_size)
    seg = segment_map(pts, rng, segmentation)
    reg: GlobalRegistration | None = None
    why: str | None = None
    elapsed = 0.0
    if vision_points is not None:
        start = time.perf_counter()
        try:
            reg = register_maps(vision_points, pts, rng, registration, segmentation, seg)
        except LocalizationError as exc:
            why = str(exc)
        elapsed = time.perf_counter() - start
    objects = seg
    if reg is not None:
        # the registered maps merged and segmented again: the drone's view joins
        # what the LiDAR saw of a stone in pieces (section 4.4, step 6)
        merged = np.vstack([pts, apply_T(reg.T_target_source, as_points(vision_points))])
        objects = segment_map(
            lidar_map(merged, voxel_size=segmentation.voxel_size), rng, segmentation
        )
    plane = np.asarray(seg.ground_plane, dtype=float)
    plane = plane if plane[2] >= 0 else -plane
    db = add_segments(
        ObjectDatabase(), [s.points for s in objects.segments], segmentation.voxel_size, plane
    )
    return Perception(pts, seg, objects, reg, why, elapsed, db)
