"""Error terms of a spinning LiDAR beyond white range noise, and the sensor's motion in a scan.

Each term is what a field scan has and a plain ray cast has not:

* **Channel range bias** (``channel_bias_sigma``): every laser channel reads a
  constant offset that its factory calibration leaves and that shifts with the
  temperature and the ambient light; it holds over a run and changes between
  runs. Drawn per channel and run (:func:`draw_channel_bias`). Spinning
  LiDARs of this class state a range *accuracy* of a few centimetres (+-3 cm
  is common) beside a range *precision* of about one; the bias lives in that
  difference. It is the term that makes two runs
  from the same pose disagree, which white noise averaged over a scan's tens
  of thousands of points cannot: paper 000's table I (a stationary sensor,
  runs at different times of day outdoors).
* **Incidence angle** (``beam_divergence``): the beam's footprint on a surface
  seen at incidence ``theta`` spreads the return over a depth of
  ``range * divergence * tan(theta)``; the range then scatters with that
  depth's standard deviation (uniform over it: ``/ sqrt(12)``) on top of the
  white noise (Soudarissanane et al. 2011, *Scanning geometry: influencing
  factor on the quality of terrestrial laser scanning points*; Lichti 2007,
  on the footprint of terrestrial laser scanners). Returns beyond
  ``max_incidence_deg`` are too weak and are dropped.
* **Clutter** (``clutter_fraction``): a share of the rays returns early from
  what no map holds (vegetation moving in the wind, people, dust): at a range
  uniform between the minimum range and the surface's.
* **Motion in the scan** (:func:`column_poses`): a revolution takes
  ``1 / rate_hz``; a sensor moving at a constant twist fires each column from
  another pose, and the driver stacks the columns into one scan in the sensor
  frame of each firing (no de-skewing), stamped at mid-revolution.

The map the scans are matched to has its own error: built from scans
registered one after the other, it drifts (:mod:`fabflow.sensors.site_map`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.transforms.se3 import perturb

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LidarErrorModel:
    """The LiDAR error terms of the module docstring (metres, radians).

    Attributes
    ----------
    channel_bias_sigma
        Standard deviation of each channel's range offset, per run (metres).
    beam_divergence
        Full beam divergence (radians) of the incidence-angle term; 0 switches it off.
    max_incidence_deg
        Returns hitting a surface more obliquely than this are dropped (degrees;
        90 keeps every return).
    clutter_fraction
        Share of rays returning early from unmapped clutter.
    """

    channel_bias_sigma: float = 0.0
    beam_divergence: float = 0.0
    max_incidence_deg: float = 90.0
    clutter_fraction: float = 0.0

    def __post_init__(self) -> None:
        values = (self.channel_bias_sigma, self.beam_divergence, self.clutter_fraction)
        if not all(np.isfinite(v) and v >= 0 for v in values) or self.clutter_fraction >= 1:
            raise InputError(
                "LiDAR errors need finite channel_bias_sigma, beam_divergence >= 0 and "
                "clutter_fraction in [0, 1)"
            )
        if not 0 < self.max_incidence_deg <= 90:
            raise InputError("LiDAR errors need 0 < max_incidence_deg <= 90")


GRAZING_COS = float(np.cos(np.radians(89.0)))
"""Incidences beyond 89 deg count as 89 deg: the footprint's spread stays finite (a
return that grazing is weak, and dropped at the model's ``max_incidence_deg``)."""

NO_ERRORS = LidarErrorModel()
"""White range noise only (the ray cast as it was)."""


def draw_channel_bias(
    errors: LidarErrorModel, n_beams: int, rng: np.random.Generator
) -> FloatArray:
    """One run's range offset of every channel, ``(n_beams,)`` metres."""
    if errors.channel_bias_sigma == 0:
        return np.zeros(n_beams)
    return rng.normal(0.0, errors.channel_bias_sigma, n_beams)


def incidence_sigma(
    ranges: ArrayLike, cos_incidence: ArrayLike, beam_divergence: float
) -> FloatArray:
    """Range standard deviation (metres) of the footprint at incidence ``acos(cos_incidence)``.

    Parameters
    ----------
    ranges
        True ranges (metres).
    cos_incidence
        Cosine of the angle between the ray and the surface normal, in (0, 1].
    beam_divergence
        Full beam divergence (radians).

    Returns
    -------
    numpy.ndarray
        Standard deviations (metres), the shape of ``ranges`` and ``cos_incidence``
        broadcast; incidences beyond 89 deg count as 89 deg.
    """
    c = np.clip(np.abs(np.asarray(cos_incidence, dtype=float)), GRAZING_COS, 1.0)
    tan = np.sqrt((1.0 - c) * (1.0 + c)) / c  # 1 - c is exact near normal incidence
    return np.asarray(ranges, dtype=float) * beam_divergence * tan / np.sqrt(12.0)


def column_poses(
    T_world_lidar: ArrayLike, twist: ArrayLike, n_columns: int, rate_hz: float
) -> FloatArray:
    """The sensor pose at each column's firing, ``(n_columns, 4, 4)`` (world frame, metres).

    Parameters
    ----------
    T_world_lidar
        4x4 pose at mid-revolution (the scan's stamp).
    twist
        ``(6,)`` constant velocity during the revolution: linear (m/s) then angular
        (rad/s), both in the world frame, the rotation about the sensor's origin.
    n_columns, rate_hz
        Columns per revolution and revolutions per second.

    Returns
    -------
    numpy.ndarray
        ``(n_columns, 4, 4)`` poses: ``perturb(T, t * twist)`` at each column's time
        ``t`` from the stamp.
    """
    T = np.asarray(T_world_lidar, dtype=float).reshape(4, 4)
    w = np.asarray(twist, dtype=float).reshape(6)
    t = (np.arange(n_columns) + 0.5) / (n_columns * rate_hz) - 0.5 / rate_hz
    return perturb(T, t[:, None] * w[None])
