"""The print head's LiDAR: a simulated scan of the site and its scan-to-map ICP pose.

The LiDAR (paper 000: a Hesai QT64) sits upright above the nozzle. Every
revolution (10 Hz) is ray-cast against the site's mesh from the sensor's true
pose and registered to the site map by point-to-plane ICP from the fused
estimate at the scan's time; the result, a nozzle pose with its covariance,
reaches the filter one processing latency later. The simulated scan uses a
sparser beam pattern than the real sensor (every fourth beam, 4 deg azimuth
steps instead of 0.6 deg, about 1,000 returns: the ICP keeps an even subsample
of 300 points of the scan anyway) so that a run stays far faster
than real time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

from fabflow.errors import LocalizationError
from fabflow.positioning.icp import icp
from fabflow.positioning.scan_map import ScanMap
from fabflow.sensors.lidar import HESAI_QT64, LidarModel, simulate_scan
from fabflow.transforms.se3 import compose_covariance, inv_T, make_T
from fabflow.transforms.so3 import exp_so3

FloatArray = NDArray[np.float64]

TRACKING_LIDAR = LidarModel(
    n_beams=HESAI_QT64.n_beams // 4,
    vertical_fov_deg=HESAI_QT64.vertical_fov_deg,
    horizontal_resolution_deg=4.0,
    max_range=HESAI_QT64.max_range,
    min_range=HESAI_QT64.min_range,
    range_sigma=HESAI_QT64.range_sigma,
    rate_hz=HESAI_QT64.rate_hz,
)
"""The QT64's field, range and noise with every fourth beam at a 4 deg azimuth step
(1,440 rays; see the module docstring)."""

T_TOOL_LIDAR = make_T(exp_so3([np.pi, 0.0, 0.0]), [0.0, 0.0, -0.5])
"""The LiDAR 0.5 m above the nozzle (against the tool's z, which points down), upright."""

ICP_ITERATIONS = 3
"""Iteration cap per ICP stage."""

ICP_POINTS = 300
"""Scan points kept for the ICP (an even subsample of the scan)."""

ICP_SCHEDULE = (0.1,)
"""Correspondence distance of the tracking ICP (metres): it starts from the fused
estimate, a few millimetres off."""


@dataclass(frozen=True, eq=False)
class IcpFix:
    """One LiDAR pose fix of the nozzle.

    Attributes
    ----------
    t
        The scan's time (s).
    T_world_tool
        The nozzle's pose from the ICP (world frame).
    covariance
        Its 6x6 covariance (fabflow's pose error, world frame; m^2, rad^2): the
        ICP's plus the map's.
    ok
        The ICP converged with enough overlap to be used.
    """

    t: float
    T_world_tool: FloatArray
    covariance: FloatArray
    ok: bool


def lidar_fix(
    scene: trimesh.Trimesh,
    site_map: ScanMap,
    t: float,
    T_world_tool_true: FloatArray,
    T_world_tool_guess: FloatArray,
    rng: np.random.Generator,
    model: LidarModel = TRACKING_LIDAR,
) -> IcpFix:
    """Scan from the true pose, then localize the scan in the map from the guess.

    Parameters
    ----------
    scene
        The site's mesh (world frame).
    site_map
        The map the machine localizes in.
    t
        The scan's time (s).
    T_world_tool_true, T_world_tool_guess
        The nozzle's true pose and the estimate the ICP starts from.
    rng
        The range noise.
    model
        The LiDAR.

    Returns
    -------
    IcpFix
        The fix; ``ok`` is ``False`` (and the pose the guess) when the scan found
        too little of the map.
    """
    scan = simulate_scan(scene, T_world_tool_true @ T_TOOL_LIDAR, rng, model)
    pts = scan.points
    if len(pts) > ICP_POINTS:
        pts = pts[np.linspace(0, len(pts) - 1, ICP_POINTS).astype(np.intp)]
    init = T_world_tool_guess @ T_TOOL_LIDAR
    if len(pts) < 50:
        return IcpFix(t, T_world_tool_guess, np.eye(6), False)
    try:
        r = icp(
            pts,
            site_map.target,
            init=init,
            max_correspondence_distance=ICP_SCHEDULE,
            max_iterations=ICP_ITERATIONS,
            workers=1,
        )
    except LocalizationError:  # too few correspondences: no fix from this scan
        return IcpFix(t, T_world_tool_guess, np.eye(6), False)
    T_lidar_tool = inv_T(T_TOOL_LIDAR)
    T_tool = r.T @ T_lidar_tool
    C_lidar = r.covariance
    if site_map.map_covariance is not None:
        C_lidar = C_lidar + site_map.map_covariance
    C = compose_covariance(r.T, C_lidar, T_lidar_tool, None)
    ok = bool(r.fitness > 0.3 and np.all(np.isfinite(C)) and np.all(np.isfinite(T_tool)))
    return IcpFix(t, T_tool, C, ok)
