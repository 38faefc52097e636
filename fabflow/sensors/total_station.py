"""Simulated total station readings: noisy ``Hz``, ``V`` and slope distances of true points.

The noise follows the instrument's data-sheet accuracy model
(:class:`fabflow.positioning.polar.Instrument`): independent normal errors of
the angles and of the distance (``a + b * sd``), plus, where set, the prism's
centring (per sighting) and the atmosphere's scale error (per set-up).
"""

from __future__ import annotations

import numpy as np

from fabflow.positioning.polar import (
    Instrument,
    cartesian_to_polar,
    polar_covariance,
    polar_to_cartesian,
)


def simulate_polar(
    points: np.ndarray,
    instrument: Instrument,
    rng: np.random.Generator,
    instrument_height: float = 0.0,
    prism_height: float | np.ndarray = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy ``(hz, v, sd)`` readings of true target ``points`` (``(..., 3)``, instrument frame).

    Angle and distance errors are drawn independently from zero-mean normals
    with the instrument's stated standard deviations. With the instrument's
    ``centring_sigma`` each sighted prism's optical centre lies off its point by
    a normal offset per axis; with ``atmosphere_ppm`` one scale error (drawn once
    per call: one set-up's readings) stretches every distance.
    """
    points = np.asarray(points, dtype=float)
    if instrument.centring_sigma > 0:
        points = points + rng.normal(0.0, instrument.centring_sigma, points.shape)
    hz, v, sd = cartesian_to_polar(points, instrument_height, prism_height)
    if instrument.atmosphere_ppm > 0:
        sd = sd * (1.0 + rng.normal(0.0, instrument.atmosphere_ppm * 1e-6))
    hz = hz + rng.normal(0.0, instrument.angle_sigma, np.shape(hz))
    v = v + rng.normal(0.0, instrument.angle_sigma, np.shape(v))
    sd = sd + rng.normal(0.0, 1.0, np.shape(sd)) * instrument.sigma_distance(sd)
    return np.mod(hz, 2.0 * np.pi), v, sd


def measure_points(
    points_instrument: np.ndarray,
    instrument: Instrument,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Simulate measuring ``points_instrument`` and return the measured points and covariances.

    Parameters
    ----------
    points_instrument
        ``(..., 3)`` true prism positions in the instrument frame (metres).
    instrument
        The accuracy model.
    rng
        Source of the measurement noise.

    Returns
    -------
    points, cov
        ``(..., 3)`` measured points and ``(..., 3, 3)`` their covariances from
        the readings (instrument frame).
    """
    hz, v, sd = simulate_polar(points_instrument, instrument, rng)
    return polar_to_cartesian(hz, v, sd), polar_covariance(hz, v, sd, instrument)
