"""LiDAR scan-to-map localization of the robot base, simulated or from files.

:func:`localize_station` scans the simulated site (:mod:`fabflow.sensors`) from
the true platform pose and registers the scan to the site map from the planned
one (``fabflow build`` and the simulator; :func:`simulate_station` and
:func:`estimate_station` are its two halves, for fault injection);
:func:`localize_files` registers a measured scan file to a map file
(``fabflow localize icp``). The estimator is
:func:`fabflow.positioning.scan_matching.localize_scan`.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from fabflow.design.elements import Element
from fabflow.errors import FabflowError
from fabflow.localize.report import check_options
from fabflow.localize.site import parking_accuracy, site_obstacles
from fabflow.positioning.pointcloud_io import read_point_cloud
from fabflow.positioning.result import BasePose
from fabflow.positioning.scan_map import ScanMap, load_map
from fabflow.positioning.scan_matching import ScanLocalization, localize_scan, to_base_pose
from fabflow.project import IcpSetup, Platform, Project
from fabflow.robots import platform
from fabflow.sensors.lidar import HESAI_QT64, simulate_scan
from fabflow.sensors.site_map import simulated_site_map, with_as_built
from fabflow.sensors.site_scene import site_scene
from fabflow.transforms.se3 import inv_T, perturb


def site_map(project: Project, seed: int | None = None) -> ScanMap:
    """The map the project's scans are matched to: its map file's, or the map a
    simulated mapping run of its site builds (:func:`~fabflow.sensors.site_map.simulated_site_map`:
    ground, landmarks and site obstacles, no blocks).

    ``seed``: ``None`` gives the project's one simulated map (seed 0, kept per
    process); a number, a mapping run of its own with its range errors and
    channel biases (and its registrations, with ``localization.icp.map_drift``),
    built and not kept (a study draws one per run). A file map ignores it.
    """
    setup = project.localization.icp or IcpSetup()
    if setup.map is not None:
        return _cached_file_map(str(setup.map), setup.map_voxel_size)
    boxes, prisms = site_obstacles(project)
    build = simulated_site_map if seed is None else simulated_site_map.__wrapped__
    return build(
        boxes,  # type: ignore[arg-type]
        setup.map_voxel_size,
        0 if seed is None else seed,
        None,
        prisms,  # type: ignore[arg-type]
        setup.lidar_errors(),
        setup.map_drift,
    )


COARSE_REACH = 10.0
"""Range (metres) of a typical scan point, at which a heading error of the initial
guess is judged for the coarse stage (:func:`coarse_schedule`)."""


def coarse_schedule(setup: IcpSetup, parking: tuple[float, float] | None) -> tuple[float, float]:
    """Correspondence distances of the coarse ICP stage (metres).

    Wide enough to pull in how far the initial guess can be off, three sigma of the
    parking accuracy ``(xy metres, heading radians)`` with the heading turning a
    scan point :data:`COARSE_REACH` away, and no wider: on a site of identical
    houses a wider reach matches one house's walls with the next's. Between
    ``max_correspondence_distance`` and four times it; four times without a parking
    accuracy (a guess given by hand).
    """
    d = setup.max_correspondence_distance
    if parking is None:
        return 4.0 * d, d
    reach = 3.0 * (parking[0] + parking[1] * COARSE_REACH)
    return float(np.clip(reach, d, 4.0 * d)), d


def _localize_scan(
    scan: np.ndarray,
    scan_map: ScanMap,
    T_init: np.ndarray,
    setup: IcpSetup,
    parking: tuple[float, float] | None = None,
) -> ScanLocalization:
    """Register a scan to the map from ``T_init`` with the project's ICP settings; the
    coarse stage sized by the ``parking`` accuracy (:func:`coarse_schedule`)."""
    return localize_scan(
        scan,
        scan_map,
        T_init,
        voxel_size=setup.voxel_size,
        min_fitness=setup.min_fitness,
        max_rmse=setup.max_rmse,
        min_structure_fitness=setup.min_structure_fitness,
        coarse_schedule=coarse_schedule(setup, parking),
        channel_bias_sigma=setup.channel_bias_sigma,
        beam_elevations=HESAI_QT64.elevations(),
    )


@functools.lru_cache(maxsize=4)
def _cached_file_map(path: str, voxel_size: float) -> ScanMap:
    return load_map(path, voxel_size)


def file_map(project: Project) -> ScanMap | None:
    """The map file the project names (``localization.icp.map``), read and prepared once
    per process; ``None`` when the map is simulated.

    A Monte Carlo study reads it where it is prepared and hands it to every run
    (:func:`localize_station`'s ``scan_map``), so that no worker opens the file.

    Raises
    ------
    InputError
        An unreadable or malformed map file (naming it and the line).
    """
    setup = project.localization.icp or IcpSetup()
    if setup.map is None:
        return None
    return _cached_file_map(str(setup.map), setup.map_voxel_size)


@dataclass(frozen=True)
class StationScan:
    """What the platform's LiDAR delivers at a station, and what it is matched to.

    Attributes
    ----------
    scan
        ``(N, 3)`` scan points in the LiDAR frame (metres).
    scan_map
        The map the scan is registered to (world frame).
    T_init
        4x4 initial guess of the LiDAR pose in the world: the planned station.
    T_base_lidar
        4x4 LiDAR pose in the arm base frame at the station's lift.
    quality
        Figures stored with the result (scan size, map source).
    """

    scan: np.ndarray
    scan_map: ScanMap
    T_init: np.ndarray
    T_base_lidar: np.ndarray
    quality: dict[str, Any]


def localize_station(
    project: Project,
    T_world_base: ArrayLike,
    rng: np.random.Generator,
    station_id: str | None = None,
    built: Sequence[Element] = (),
    lift: float = 0.0,
    scan_map: ScanMap | None = None,
) -> BasePose:
    """Simulate LiDAR scan-to-map localization of a parked platform.

    :func:`simulate_station` then :func:`estimate_station`: the platform's LiDAR
    (``localization.icp.T_platform_lidar``) scans the simulated site (ground,
    landmarks, the project's box and polygon obstacles and the blocks in
    ``built``) from the true pose; the scan is localized against the map
    (``localization.icp.map``, or a simulated map of the site without blocks),
    starting from the true pose perturbed by the driving error
    (``simulation.driving_error``, ``simulation.driving_heading_error_deg``), i.e.
    from where the platform was meant to park. With ``localization.icp.map_as_built``
    (default) the blocks in ``built`` are added to the map at their design poses
    (:func:`with_as_built`).

    Parameters
    ----------
    project
        The project.
    T_world_base
        4x4 true arm base pose (metres).
    rng
        Random generator (range noise and the initial-guess error).
    station_id
        Stored in the result.
    built
        Elements built so far (in the scan, not in the map).
    lift
        Lift height of the station (metres): the LiDAR sits on the platform and
        does not move with the lift.
    scan_map
        The project's map, already read (:func:`file_map`); read here when ``None``.

    Returns
    -------
    BasePose
        The estimated ``T_world_base`` with covariance, quality figures and the
        scan's integrity record unchanged: status ``"failed"`` (with the reason)
        when the scan fails the fitness, RMSE, structure or geometry checks.

    Raises
    ------
    LocalizationError
        When no pose can be computed (too few scan points or correspondences).
    """
    data = simulate_station(project, T_world_base, rng, built, lift, scan_map)
    return estimate_station(project, data, station_id)


def simulate_station(
    project: Project,
    T_world_base: ArrayLike,
    rng: np.random.Generator,
    built: Sequence[Element] = (),
    lift: float = 0.0,
    scan_map: ScanMap | None = None,
) -> StationScan:
    """The scan of a simulated station and its map (see :func:`localize_station`;
    ``scan_map``: the project's map already read, read here when ``None``)."""
    setup = project.localization.icp or IcpSetup()
    T_platform_base = platform.T_platform_base_at(
        project.robot.platform.T_platform_base.matrix(), lift
    )
    T_platform_lidar = setup.T_platform_lidar.matrix()
    T_base_lidar = inv_T(T_platform_base) @ T_platform_lidar
    T_true = np.asarray(T_world_base, dtype=float) @ T_base_lidar

    boxes, prisms = site_obstacles(project)
    scene = site_scene(built=built, obstacles=boxes, prisms=prisms)
    scan = simulate_scan(scene, T_true, rng, HESAI_QT64, setup.lidar_errors())

    sim = project.simulation
    err = np.zeros(6)
    err[:2] = rng.normal(0.0, sim.driving_error, 2)
    err[5] = rng.normal(0.0, np.radians(sim.driving_heading_error_deg))
    # the planned pose: a driving error of the platform, seen at the sensor
    T_world_platform = platform.T_world_platform_of(
        T_world_base, lift, project.robot.platform.T_platform_base.matrix()
    )
    T_init = perturb(T_world_platform, err) @ T_platform_lidar

    if scan_map is None:
        scan_map = site_map(project)
    if setup.map_as_built:
        scan_map = with_as_built(scan_map, built, rng, setup.as_built_sigma)
    return StationScan(
        scan=scan.points,
        scan_map=scan_map,
        T_init=T_init,
        T_base_lidar=T_base_lidar,
        quality={
            "n_scan_points": len(scan),
            "map": str(setup.map) if setup.map else "simulated",
            "map_as_built_blocks": sum(e.extents is not None for e in built)
            if setup.map_as_built
            else 0,
        },
    )


def estimate_station(
    project: Project, data: StationScan, station_id: str | None = None
) -> BasePose:
    """The base pose from a station's scan, with its checks (see :func:`localize_station`)."""
    setup = project.localization.icp or IcpSetup()
    loc = _localize_scan(data.scan, data.scan_map, data.T_init, setup, parking_accuracy(project))
    return to_base_pose(loc, data.T_base_lidar, station=station_id, quality=data.quality)


def localize_files(
    scan_path: str | Path,
    map_path: str | Path,
    init: tuple[float, float, float],
    project: Project | None = None,
    lift: float = 0.0,
    station: str | None = None,
) -> BasePose:
    """Localize a scan file against a map file (the ``fabflow localize icp`` command).

    Parameters
    ----------
    scan_path
        One LiDAR scan in the sensor frame (PLY, XYZ, CSV; metres).
    map_path
        The site map in the world frame (PLY, XYZ, CSV; metres).
    init
        Planned platform pose ``(x, y, yaw)`` on the ground (metres, metres, degrees).
    project
        Takes the LiDAR mounting, arm mounting and thresholds from
        ``localization.icp`` and ``robot.platform``; defaults when ``None``.
    lift
        Lift height of the arm above its lowest position (metres).
    station
        Station id stored in the result.

    Returns
    -------
    BasePose
        The base pose with the scan's integrity record unchanged (status
        ``"failed"`` with the reason when a check fails).

    Raises
    ------
    InputError
        An unreadable scan or map file (naming it and the line), or ``init`` or
        ``lift`` outside :data:`fabflow.localize.report.OPTION_BOUNDS`.
    LocalizationError
        When no pose can be computed (too few scan points or correspondences),
        naming the scan file.
    """
    check_options({"init": init, "lift": lift})
    setup = (project.localization.icp if project is not None else None) or IcpSetup()
    mounting = (project.robot.platform if project is not None else Platform()).T_platform_base
    T_platform_base = platform.T_platform_base_at(mounting.matrix(), lift)
    T_platform_lidar = setup.T_platform_lidar.matrix()
    x, y, yaw_deg = init
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T_world_platform = np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    scan = read_point_cloud(scan_path).points
    scan_map = load_map(map_path, setup.map_voxel_size)
    try:
        loc = _localize_scan(scan, scan_map, T_world_platform @ T_platform_lidar, setup)
    except FabflowError as exc:
        if exc.source is not None:
            raise
        # the scan gave no pose (too few points, no correspondences): name it
        raise type(exc)(exc.message, scan_path, exc.location) from None
    return to_base_pose(
        loc,
        inv_T(T_platform_base) @ T_platform_lidar,
        station=station,
        quality={"n_scan_points": len(scan), "map": str(map_path), "scan": str(scan_path)},
    )
