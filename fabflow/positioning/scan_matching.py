"""LiDAR scan-to-map localization (paper 000, section III-C).

Offline, :func:`build_map` registers several scans of the site into one map
(each new scan is aligned by ICP to the map merged so far, starting from its
odometry guess; the first scan anchors the map frame), merges and voxelizes them
and estimates normals. Online, :func:`localize_scan` aligns a new scan to the map
from a rough initial pose (the platform's planned station) with a coarse-to-fine
point-to-plane ICP and checks the result (fitness, inlier RMSE, structure fitness,
the weakest direction of the information). The outcome is an
:class:`~fabflow.positioning.integrity.Integrity` record on every result: a pose
that was computed but fails a check is returned with status ``"failed"`` and the
reason, never as a silently wrong pose; only a scan that yields no pose at all
(too few points, no correspondences) raises
:class:`~fabflow.errors.LocalizationError`.

The covariance is the blocked sandwich of :mod:`fabflow.positioning.icp` over
cubes of :data:`COVARIANCE_BLOCK`. A global test of the variance factor is not
meaningful here: thousands of residuals whose errors are shared within surfaces
are far from independent, so the redundancy is recorded as information only.
:mod:`fabflow.localize.icp` joins the simulated station and files to these.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.icp import (
    IcpResult,
    IcpTarget,
    icp,
    prepare_target,
)
from fabflow.positioning.icp_weakness import WeakDirection, weakest_direction
from fabflow.positioning.integrity import Integrity
from fabflow.positioning.lidar_channels import channel_of
from fabflow.positioning.pointcloud import as_points, estimate_normals, voxel_downsample
from fabflow.positioning.pointcloud_io import read_point_cloud
from fabflow.positioning.result import BasePose
from fabflow.transforms.se3 import apply_T, compose_covariance, inv_T

FloatArray = NDArray[np.float64]

COARSE_SCHEDULE = (2.0, 0.5)
"""Correspondence distances (m) of the coarse stage, on a 4x coarser voxel grid."""
FINE_SCHEDULE = (0.1,)
"""Correspondence distances (m) of the fine stage, on the scan voxel grid."""
MIN_CONDITION = 1e-5
"""Smallest accepted ratio of smallest to largest information eigenvalue."""
COVARIANCE_BLOCK = 1.0
"""Edge (m) of the cubes of scan points whose residual errors the covariance treats
as shared: the scale of the surfaces of a site (a column, a pallet, a stretch of
wall or railing). Errors that do not average over the points of one surface (the
map's error there, voxel-centroid bias along edges, facets and noisy grazing
returns) correlate residuals metres apart; see docs/icp.md for the measurement."""
WEAK_SIGMA_FRACTION = 1.0 / 3.0
"""A direction whose sigma exceeds this fraction of the last correspondence
distance (the Huber kernel's inlier scale) is not held by the inliers."""
MAX_STORED_RESIDUALS = 1000
MIN_STEP = 1e-4
"""ICP stops when an update moves no scan point by more than this (metres)."""


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
    """

    target: IcpTarget
    coarse: IcpTarget
    voxel_size: float
    T_world_scans: tuple[FloatArray, ...] = ()
    map_covariance: FloatArray | None = None
    point_groups: NDArray[np.intp] | None = None
    group_sigma: float = 0.0

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
    if n is None:
        n = estimate_normals(p, k=20)  # type: ignore[assignment]
    pc, nc = voxel_downsample(p, 4 * voxel_size, n)
    return ScanMap(
        target=prepare_target(p, n),
        coarse=prepare_target(pc, nc) if len(pc) >= 100 else prepare_target(p, n),
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


@dataclass(frozen=True, eq=False)
class ScanLocalization:
    """A scan localized in the map.

    Attributes
    ----------
    T_world_lidar
        4x4 sensor pose in the map (world) frame.
    covariance
        6x6 covariance of ``T_world_lidar`` (fabflow convention, world frame).
    icp
        The final ICP result (fitness, inlier RMSE, iterations, residuals).
    n_points
        Number of scan points used after voxelizing.
    structure_fitness
        Fitness of the points near non-horizontal map surfaces (see
        :func:`structure_fitness`).
    integrity
        The checks and their outcome: status ``"ok"``, or ``"failed"`` with the
        reason (do not use the pose); the figures are in ``integrity.checks``.
    weakest
        The least constrained direction of the pose (world frame).
    """

    T_world_lidar: FloatArray
    covariance: FloatArray
    icp: IcpResult
    n_points: int
    structure_fitness: float
    integrity: Integrity
    weakest: WeakDirection


def localize_scan(
    scan_lidar: ArrayLike,
    scan_map: ScanMap | IcpTarget,
    T_world_lidar_init: ArrayLike,
    voxel_size: float = 0.05,
    min_fitness: float = 0.25,
    max_rmse: float = 0.03,
    coarse_schedule: Sequence[float] | None = COARSE_SCHEDULE,
    fine_schedule: Sequence[float] = FINE_SCHEDULE,
    max_points: int = 6000,
    min_structure_fitness: float = 0.5,
    covariance_block: float | None = COVARIANCE_BLOCK,
    channel_bias_sigma: float = 0.0,
    beam_elevations: ArrayLike | None = None,
) -> ScanLocalization:
    """Localize one scan in the map from a rough initial pose.

    Two stages: point-to-plane ICP on the scan voxelized at ``4 * voxel_size``
    with correspondence distances ``coarse_schedule`` (pulls in initial errors of
    0.5 m and 10 deg), then on the scan voxelized at ``voxel_size`` with
    ``fine_schedule``. A Huber kernel (scale a third of the correspondence
    distance) discounts what the map does not hold (new construction, people,
    machines). Tracking at 10 Hz from the previous pose
    (initial errors of a few centimetres) can skip the coarse stage.

    Parameters
    ----------
    scan_lidar
        ``(N, 3)`` scan points in the sensor frame (metres).
    scan_map
        The map (world frame).
    T_world_lidar_init
        Initial guess of the sensor pose in the world.
    voxel_size
        Voxel grid of the scan for the fine stage (metres).
    coarse_schedule
        Correspondence distances of the coarse stage (metres); ``None`` skips it.
    fine_schedule
        Correspondence distances of the fine stage (metres).
    max_points
        At most this many voxelized scan points per stage (an even subsample);
        the coarse stage uses a third of it.
    min_fitness, max_rmse
        Acceptance thresholds: fraction of fine-stage scan points with a map point
        within the last correspondence distance, and RMS point-to-plane distance of
        those (metres).
    min_structure_fitness
        Required fitness of the points on walls, columns and other non-horizontal
        surfaces (see :func:`structure_fitness`).
    covariance_block
        Edge of the covariance blocks (metres; ``None``: independent points).
    channel_bias_sigma, beam_elevations
        Standard deviation of the range bias each laser channel keeps over a
        run (metres; :mod:`fabflow.sensors.lidar_errors`), and the channels'
        elevations in the sensor frame (radians, ascending): each scan point
        belongs to the nearest, and the covariance counts the bias shared by a
        channel's points (:func:`~fabflow.positioning.lidar_channels.channel_of`,
        :func:`~fabflow.positioning.icp.icp`'s ``ray_groups``).

    Returns
    -------
    ScanLocalization
        The pose, its covariance and its integrity: status ``"failed"`` (with the
        check, its value and its threshold in the reason) when the fine ICP has not
        converged within its iterations, when the fitness is below
        ``min_fitness``, the inlier RMSE above ``max_rmse``, the structure fitness
        below ``min_structure_fitness``, the information condition below
        :data:`MIN_CONDITION`, or the sigma of the weakest direction above
        :data:`WEAK_SIGMA_FRACTION` of the last fine correspondence distance
        (e.g. only the ground in view, or a corridor).

    Raises
    ------
    LocalizationError
        No pose at all: fewer than 100 scan points after voxelizing, or too few
        correspondences for ICP to run.
    """
    scan_map_covariance, groups, group_sigma = None, None, 0.0
    if isinstance(scan_map, ScanMap):
        target, coarse_target = scan_map.target, scan_map.coarse
        scan_map_covariance = scan_map.map_covariance
        groups, group_sigma = scan_map.point_groups, scan_map.group_sigma
    else:
        target = coarse_target = scan_map
    scan = as_points(scan_lidar, "scan")
    fine = _thin(voxel_downsample(scan, voxel_size)[0], max_points)
    if len(fine) < 100:
        raise LocalizationError(f"the scan holds only {len(fine)} points after voxelizing")
    T = np.asarray(T_world_lidar_init, dtype=float).reshape(4, 4)
    if coarse_schedule is not None:
        coarse = _thin(voxel_downsample(scan, 4 * voxel_size)[0], max(max_points // 3, 100))
        T = icp(
            coarse,
            coarse_target,
            init=T,
            max_correspondence_distance=coarse_schedule,
            kernel="huber",
            min_step=MIN_STEP,
        ).T
    res = icp(
        fine,
        target,
        init=T,
        max_correspondence_distance=fine_schedule,
        kernel="huber",
        min_step=MIN_STEP,
        covariance_block=covariance_block,
        ray_groups=None if beam_elevations is None else channel_of(fine, beam_elevations),
        ray_sigma=channel_bias_sigma,
        target_groups=groups,
        target_sigma=group_sigma,
    )
    structure = structure_fitness(fine, target, res.T, float(fine_schedule[-1]))
    weak = weakest_direction(res.information)
    limits = {
        "min_fitness": min_fitness,
        "max_rmse": max_rmse,
        "min_structure_fitness": min_structure_fitness,
        "max_weakest_sigma": WEAK_SIGMA_FRACTION * float(fine_schedule[-1]),
    }
    return ScanLocalization(
        T_world_lidar=res.T,
        covariance=res.covariance
        if scan_map_covariance is None
        else res.covariance + scan_map_covariance,
        icp=res,
        n_points=len(fine),
        structure_fitness=structure,
        integrity=scan_integrity(res, structure, weak, limits, covariance_block),
        weakest=weak,
    )


def scan_integrity(
    res: IcpResult,
    structure: float,
    weak: WeakDirection,
    limits: dict[str, float],
    covariance_block: float | None = COVARIANCE_BLOCK,
) -> Integrity:
    """The integrity record of a scan localization: every check, and which failed.

    Parameters
    ----------
    res
        The final ICP.
    structure
        Its structure fitness.
    weak
        The weakest direction of its information.
    limits
        ``min_fitness``, ``max_rmse`` (m), ``min_structure_fitness`` and
        ``max_weakest_sigma`` (m).
    covariance_block
        Recorded with the figures.

    Returns
    -------
    Integrity
        Status ``"ok"``, or ``"failed"`` with a reason naming each failed check, its
        value and its threshold. ``redundancy`` is ``n_inliers - 6``, for
        information only (no global test; see the module docstring).
    """
    failed: dict[str, str] = {}
    if not res.converged:
        # still moving when the iterations ran out: not at a minimum, so neither the
        # pose nor its covariance can be trusted (a start beyond the pull-in range)
        failed["converged"] = (
            f"ICP did not converge in {res.iterations} iterations (the initial pose is "
            "too far off, or the scan slides along the map)"
        )
    if res.fitness < limits["min_fitness"]:
        failed["fitness"] = (
            f"ICP fitness {res.fitness:.3f} is below the required {limits['min_fitness']:.3f} "
            "(the scan does not match the map: wrong initial pose, wrong map, or the site "
            "has changed)"
        )
    if res.inlier_rmse > limits["max_rmse"]:
        failed["inlier_rmse"] = (
            f"ICP inlier RMSE {res.inlier_rmse * 1000:.1f} mm exceeds the allowed "
            f"{limits['max_rmse'] * 1000:.1f} mm"
        )
    if structure < limits["min_structure_fitness"]:
        failed["structure_fitness"] = (
            f"only {structure:.0%} of the scan points on walls and other non-horizontal "
            f"surfaces match the map (required {limits['min_structure_fitness']:.0%}), so the "
            "pose is held by the ground alone and is likely wrong in x, y and heading"
        )
    top = max(float(weak.eigenvalues[-1]), 1e-300)
    n_weak = int(np.sum(weak.eigenvalues < MIN_CONDITION * top))
    if res.condition < MIN_CONDITION:
        more = f" and {n_weak - 1} more direction(s)" if n_weak > 1 else ""
        failed["condition"] = (
            f"the scan geometry does not constrain {weak.label}{more} (information "
            f"condition {res.condition:.1e} below {MIN_CONDITION:.0e})"
        )
    elif weak.sigma > limits["max_weakest_sigma"]:
        failed["weakest_sigma"] = (
            f"the scan geometry hardly constrains {weak.label} (sigma "
            f"{weak.sigma * 1000:.1f} mm along it, allowed "
            f"{limits['max_weakest_sigma'] * 1000:.1f} mm)"
        )
    checks: dict[str, Any] = {
        "converged": bool(res.converged),
        "iterations": int(res.iterations),
        "fitness": float(res.fitness),
        "structure_fitness": float(structure),
        "inlier_rmse": float(res.inlier_rmse),
        "condition": float(res.condition),
        "min_condition": MIN_CONDITION,
        **{k: float(v) for k, v in limits.items()},
        "weakest_direction": [float(x) for x in weak.vector],
        "weakest_axis": weak.label,
        "weakest_translation_share": weak.translation_share,
        "weakest_sigma": weak.sigma,
        "weakest_lever": weak.lever,
        "unconstrained_directions": n_weak,
        "n_inliers": int(res.n_inliers),
        "covariance_block": covariance_block,
        "covariance_blocks": int(res.n_blocks),
        "failed_checks": list(failed),
    }
    return Integrity(
        status="failed" if failed else "ok",
        reason="; ".join(failed.values()),
        redundancy=int(res.n_inliers) - 6,
        checks=checks,
    )


def structure_fitness(
    source: FloatArray, target: IcpTarget, T: FloatArray, max_distance: float, reach: float = 1.0
) -> float:
    """Fitness of the source points that lie near non-horizontal map surfaces.

    The ground of a site usually dominates a scan, so the overall fitness can be
    high while walls and columns, which fix x, y and heading, do not match at all.
    This is the fraction of source points whose nearest map point within
    ``reach`` metres has a normal at least 45 deg from vertical (world z up) and
    which lie within ``max_distance`` of the map. 1.0 when no such points exist.
    """
    assert target.normals is not None
    p = apply_T(T, source)
    d, idx = target.tree.query(p, k=1, distance_upper_bound=reach, workers=-1)
    near = np.isfinite(d)
    steep = np.zeros(len(p), dtype=bool)
    steep[near] = np.abs(target.normals[idx[near], 2]) < np.sqrt(0.5)
    if not steep.any():
        return 1.0
    return float(np.mean(d[steep] <= max_distance))


def _thin(points: FloatArray, max_points: int) -> FloatArray:
    """An even subsample of at most ``max_points`` points (voxel order is spatial)."""
    if len(points) <= max_points:
        return points
    return points[np.linspace(0, len(points) - 1, max_points).astype(np.int64)]


def to_base_pose(
    loc: ScanLocalization,
    T_base_lidar: ArrayLike,
    station: str | None = None,
    quality: dict[str, Any] | None = None,
) -> BasePose:
    """Turn a scan localization into the robot base pose with its covariance.

    Parameters
    ----------
    loc
        The localized sensor pose.
    T_base_lidar
        4x4 sensor mounting in the base frame (taken as exact).
    station, quality
        Stored in the result (``quality`` extends the ICP figures).

    Returns
    -------
    BasePose
        ``T_world_base`` with its covariance; ``integrity`` is ``loc.integrity``
        unchanged (a failed scan gives a failed base pose).
    """
    T_lidar_base = inv_T(np.asarray(T_base_lidar, dtype=float))
    T_world_base = loc.T_world_lidar @ T_lidar_base
    cov = compose_covariance(loc.T_world_lidar, loc.covariance, T_lidar_base, None)
    r = loc.icp.residuals
    stride = max(1, int(np.ceil(len(r) / MAX_STORED_RESIDUALS)))
    q: dict[str, Any] = {
        "fitness": float(loc.icp.fitness),
        "inlier_rmse": float(loc.icp.inlier_rmse),
        "n_inliers": int(loc.icp.n_inliers),
        "n_points": int(loc.n_points),
        "iterations": int(loc.icp.iterations),
        "converged": bool(loc.icp.converged),
        "condition": float(loc.icp.condition),
        "structure_fitness": float(loc.structure_fitness),
        "residuals_stride": stride,
        "T_world_lidar": loc.T_world_lidar.tolist(),
    }
    q.update(quality or {})
    return BasePose(
        T_world_base=T_world_base,
        covariance=0.5 * (cov + cov.T),
        method="icp",
        residuals=r[::stride].reshape(-1, 1),
        rmse=float(loc.icp.inlier_rmse),
        station=station,
        quality=q,
        integrity=loc.integrity,
    )
