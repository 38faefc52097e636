"""LiDAR scan-to-map localization (paper 000, section III-C).

The map is :mod:`fabflow.positioning.scan_map`'s (read from a file, or built
offline from several scans of the site). Online, :func:`localize_scan` aligns a
new scan to the map from a rough initial pose (the platform's planned station)
with a coarse-to-fine point-to-plane ICP and checks the result (fitness, inlier
RMSE, structure fitness, the weakest direction of the information). The outcome
is an :class:`~fabflow.positioning.integrity.Integrity` record on every result: a pose
that was computed but fails a check is returned with status ``"failed"`` and the
reason, never as a silently wrong pose; only a scan that yields no pose at all
(too few points, no correspondences) raises
:class:`~fabflow.errors.LocalizationError`.

The covariance is the blocked sandwich of :mod:`fabflow.positioning.icp` over
cubes of :data:`~fabflow.positioning.scan_map.COVARIANCE_BLOCK`, plus the errors
of the map that the map knows of (:class:`~fabflow.positioning.scan_map.ScanMap`).
A global test of the variance factor is not meaningful here: thousands of
residuals whose errors are shared within surfaces are far from independent, so
the redundancy is recorded as information only.
:mod:`fabflow.localize.icp` joins the simulated station and files to these.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import LocalizationError
from fabflow.positioning.icp import (
    IcpResult,
    IcpTarget,
    icp,
)
from fabflow.positioning.icp_weakness import WeakDirection, weakest_direction
from fabflow.positioning.integrity import Integrity
from fabflow.positioning.lidar_channels import channel_of
from fabflow.positioning.pointcloud import as_points, voxel_downsample
from fabflow.positioning.result import BasePose
from fabflow.positioning.scan_map import COVARIANCE_BLOCK, ScanMap
from fabflow.transforms.se3 import apply_T, compose_covariance, inv_T

FloatArray = NDArray[np.float64]

COARSE_SCHEDULE = (2.0, 0.5)
"""Correspondence distances (m) of the coarse stage, on a 4x coarser voxel grid."""
FINE_SCHEDULE = (0.1,)
"""Correspondence distances (m) of the fine stage, on the scan voxel grid."""
MIN_CONDITION = 1e-5
"""Smallest accepted ratio of smallest to largest information eigenvalue."""
WEAK_SIGMA_FRACTION = 1.0 / 3.0
"""A direction whose sigma exceeds this fraction of the last correspondence
distance (the Huber kernel's inlier scale) is not held by the inliers."""
MAX_STORED_RESIDUALS = 1000
MIN_STEP = 1e-4
"""ICP stops when an update moves no scan point by more than this (metres)."""


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
    scan_map_covariance, groups, group_sigma, map_rays = None, None, 0.0, None
    if isinstance(scan_map, ScanMap):
        target, coarse_target = scan_map.target, scan_map.coarse
        scan_map_covariance = scan_map.map_covariance
        groups, group_sigma = scan_map.point_groups, scan_map.group_sigma
        map_rays = scan_map.map_rays
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
        map_rays=map_rays,
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
