"""Which laser channel of a spinning LiDAR each scan point came from.

A spinning LiDAR fires its channels at fixed elevations; a point's elevation in
the sensor frame names its channel. Errors a channel shares over a run (its
range bias) then group by it (:func:`fabflow.positioning.icp.icp`'s
``ray_groups``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.positioning.pointcloud import as_points


def channel_of(points: ArrayLike, beam_elevations: ArrayLike) -> NDArray[np.intp]:
    """The laser channel of every scan point: the one whose elevation is nearest.

    Parameters
    ----------
    points
        ``(N, 3)`` finite points in the sensor frame (metres).
    beam_elevations
        ``(B,)`` channel elevations (radians, ascending, finite).

    Returns
    -------
    numpy.ndarray
        ``(N,)`` channel index of every point, into ``beam_elevations``.

    Raises
    ------
    InputError
        Points that are not ``(N, 3)`` and finite, or elevations that are not a
        non-empty, finite, ascending 1-D array.
    """
    p = as_points(points, "scan points")
    beams = np.asarray(beam_elevations, dtype=float)
    if (
        beams.ndim != 1
        or len(beams) == 0
        or not np.all(np.isfinite(beams))
        or np.any(np.diff(beams) < 0)
    ):
        raise InputError("beam elevations must be a non-empty, finite, ascending list")
    if len(beams) == 1:
        return np.zeros(len(p), dtype=np.intp)
    elevation = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    right = np.clip(np.searchsorted(beams, elevation), 1, len(beams) - 1)
    left = right - 1
    nearer_left = elevation - beams[left] < beams[right] - elevation
    return np.where(nearer_left, left, right).astype(np.intp)
