"""A spinning multi-beam LiDAR simulated by ray casting a triangle mesh.

The default model is the Hesai QT64 of paper 000: 64 beams spread evenly over a
104.2 deg vertical field (-52.1..+52.1 deg), 0.6 deg horizontal steps at 10 Hz
(600 columns, 38 400 rays per scan), 20 m maximum range, 1 cm range noise
(1 sigma, along the ray). Sensor frame: x forward, y left, z up; azimuth counted
from x towards y, elevation from the x-y plane towards z.

Ray casting uses trimesh, which picks Embree (``embreex``) when installed and a
pure-numpy intersector otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.sensors.lidar_errors import (
    NO_ERRORS,
    LidarErrorModel,
    column_poses,
    draw_channel_bias,
    incidence_sigma,
)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LidarModel:
    """Beam pattern and noise of a spinning LiDAR.

    Attributes
    ----------
    n_beams
        Number of laser channels (rows).
    vertical_fov_deg
        Lowest and highest beam elevation (degrees).
    horizontal_resolution_deg
        Azimuth step between columns (degrees).
    max_range, min_range
        Returns outside ``[min_range, max_range]`` (metres) are dropped.
    range_sigma
        Standard deviation of the range noise (metres).
    rate_hz
        Scan rate (full revolutions per second).
    """

    n_beams: int = 64
    vertical_fov_deg: tuple[float, float] = (-52.1, 52.1)
    horizontal_resolution_deg: float = 0.6
    max_range: float = 20.0
    min_range: float = 0.3
    range_sigma: float = 0.01
    rate_hz: float = 10.0

    def __post_init__(self) -> None:
        lo, hi = self.vertical_fov_deg
        if self.n_beams < 1 or lo > hi or not -90.0 <= lo <= hi <= 90.0:
            raise InputError("LiDAR model needs n_beams >= 1 and -90 <= fov_min <= fov_max <= 90")
        if self.horizontal_resolution_deg <= 0 or self.max_range <= self.min_range:
            raise InputError("LiDAR model needs a positive resolution and max_range > min_range")
        if not (self.rate_hz > 0 and self.range_sigma >= 0):
            raise InputError("LiDAR model needs rate_hz > 0 and range_sigma >= 0")

    @property
    def n_columns(self) -> int:
        """Number of azimuth steps per revolution."""
        return round(360.0 / self.horizontal_resolution_deg)

    def elevations(self) -> FloatArray:
        """Elevation of every channel (radians, ascending)."""
        return np.radians(np.linspace(*self.vertical_fov_deg, self.n_beams))

    def directions(self) -> FloatArray:
        """Unit ray directions in the sensor frame, ``(n_beams * n_columns, 3)``, beam-major.

        Computed once per model (a read-only array shared by every scan).
        """
        return _directions(self)


@cache
def _directions(model: LidarModel) -> FloatArray:
    elev = model.elevations()
    azim = np.radians(np.arange(model.n_columns) * 360.0 / model.n_columns)
    e, a = np.meshgrid(elev, azim, indexing="ij")
    ce = np.cos(e)
    out = np.stack([ce * np.cos(a), ce * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)
    out.flags.writeable = False
    return out


HESAI_QT64 = LidarModel()
"""The LiDAR of paper 000 (Hesai QT64: 64 beams, 104.2 deg vertical field, 20 m, 10 Hz)."""

VLP16 = LidarModel(
    n_beams=16,
    vertical_fov_deg=(-15.0, 15.0),
    horizontal_resolution_deg=0.2,
    max_range=100.0,
    range_sigma=0.03,
    rate_hz=10.0,
)
"""The Velodyne VLP-16 (Puck) of paper 002, after Velodyne's VLP-16 user manual
(63-9243, specifications): 16 channels 2 deg apart over -15..+15 deg, 0.1-0.4 deg
horizontal resolution at 5-20 Hz (0.2 deg at 10 Hz: 1800 columns, 28 800 rays per
scan), range up to 100 m, "typical accuracy +-3 cm", taken here as the 1-sigma
white range noise. The manual states no minimum range: the class default is kept."""


@dataclass(frozen=True, eq=False)
class LidarScan:
    """One simulated revolution.

    Attributes
    ----------
    points
        ``(N, 3)`` measured points in the sensor frame (metres), noise included.
    ranges
        ``(N,)`` measured ranges (metres).
    ray_index
        ``(N,)`` index of each return's ray in :meth:`LidarModel.directions`.
    T_world_lidar
        The true sensor pose the scan was taken from.
    face_index
        ``(N,)`` index of the scene triangle each return hit (ground truth, e.g. for
        exact normals of a simulated map).
    """

    points: FloatArray
    ranges: FloatArray
    ray_index: NDArray[np.int64]
    T_world_lidar: FloatArray
    face_index: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.points)


def simulate_scan(
    scene: trimesh.Trimesh,
    T_world_lidar: ArrayLike,
    rng: np.random.Generator,
    model: LidarModel = HESAI_QT64,
    errors: LidarErrorModel = NO_ERRORS,
    channel_bias: ArrayLike | None = None,
    twist: ArrayLike | None = None,
) -> LidarScan:
    """Cast every ray of one revolution against ``scene`` and add the range errors.

    Parameters
    ----------
    scene
        The site mesh in the world frame (see :func:`fabflow.sensors.site_scene.site_scene`).
    T_world_lidar
        4x4 sensor pose in the world (metres); with ``twist``, at mid-revolution.
    rng
        Source of the range noise (and of the channel bias when not given).
    model
        Beam pattern, range limits and white range noise.
    errors
        Channel bias, incidence-angle noise and clutter
        (:class:`~fabflow.sensors.lidar_errors.LidarErrorModel`; default none).
    channel_bias
        ``(n_beams,)`` range offset of each channel for this run (metres); drawn
        from ``errors`` when ``None`` (a new run).
    twist
        ``(6,)`` velocity of the sensor during the revolution (m/s, rad/s, world
        frame, :func:`~fabflow.sensors.lidar_errors.column_poses`); ``None``: still.

    Returns
    -------
    LidarScan
        Points in the sensor frame of each column's firing (no de-skewing); rays
        that hit nothing within range, or hit a surface beyond the largest
        incidence, are dropped.
    """
    T = np.asarray(T_world_lidar, dtype=float).reshape(4, 4)
    dirs_lidar = model.directions()
    if twist is not None:
        twist = np.asarray(twist, dtype=float)
        if twist.shape != (6,) or not np.all(np.isfinite(twist)):
            raise InputError("a scan's twist must be 6 finite numbers (m/s, rad/s)")
    if channel_bias is not None:
        channel_bias = np.asarray(channel_bias, dtype=float)
        if channel_bias.shape != (model.n_beams,) or not np.all(np.isfinite(channel_bias)):
            raise InputError(f"a scan's channel bias must be {model.n_beams} finite numbers (m)")
    if twist is None:
        dirs_world = dirs_lidar @ T[:3, :3].T
        origins = np.broadcast_to(T[:3, 3], dirs_world.shape)
    else:
        poses = column_poses(T, twist, model.n_columns, model.rate_hz)
        column = np.arange(len(dirs_lidar)) % model.n_columns
        dirs_world = np.einsum("nij,nj->ni", poses[column, :3, :3], dirs_lidar)
        origins = poses[column, :3, 3]
    if len(scene.faces) == 0:
        none = np.zeros(0, dtype=np.int64)
        return LidarScan(np.zeros((0, 3)), np.zeros(0), none, T, none)
    locations, index_ray, index_tri = scene.ray.intersects_location(
        origins, dirs_world, multiple_hits=False
    )
    index_ray = np.asarray(index_ray, dtype=np.int64)
    index_tri = np.asarray(index_tri, dtype=np.int64)
    true_range = np.linalg.norm(locations - origins[index_ray], axis=1)
    cos_inc = np.abs(np.einsum("ij,ij->i", scene.face_normals[index_tri], dirs_world[index_ray]))
    keep = (true_range >= model.min_range) & (true_range <= model.max_range)
    keep &= cos_inc >= np.cos(np.radians(errors.max_incidence_deg)) - 1e-12
    order = np.flatnonzero(keep)[np.argsort(index_ray[keep], kind="stable")]
    index_ray, true_range, cos_inc = index_ray[order], true_range[order], cos_inc[order]
    bias = draw_channel_bias(errors, model.n_beams, rng) if channel_bias is None else channel_bias
    sigma = np.hypot(
        model.range_sigma, incidence_sigma(true_range, cos_inc, errors.beam_divergence)
    )
    ranges = (
        true_range + bias[index_ray // model.n_columns] + sigma * rng.standard_normal(len(order))
    )
    if errors.clutter_fraction > 0:
        early = rng.random(len(order)) < errors.clutter_fraction
        ranges[early] = rng.uniform(model.min_range, true_range[early])
    points = dirs_lidar[index_ray] * ranges[:, None]
    return LidarScan(
        points=points,
        ranges=ranges,
        ray_index=index_ray,
        T_world_lidar=T,
        face_index=index_tri[order],
    )
