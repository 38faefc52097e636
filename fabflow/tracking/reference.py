"""The reference of a tracked print: one Hermite path through every layer, sampled at 100 Hz.

The layers of a project's print paths are joined in build order into one
polyline in the world frame (the extruder off on the joins: a lift to the next
layer) and sampled as one cubic Hermite curve at constant speed
(:func:`~fabflow.design.hermite.sample_hermite`, paper 000 section IV-B). The
print head points straight down all along (a round nozzle has no heading), so
the reference orientation is constant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fabflow.design.elements import Element
from fabflow.design.hermite import sample_hermite
from fabflow.errors import InputError
from fabflow.transforms.se3 import apply_T

FloatArray = NDArray[np.float64]

R_DOWN = np.diag([1.0, -1.0, -1.0])
"""The print head's orientation in the world: z (the nozzle's axis) down, x along world x."""


@dataclass(frozen=True, eq=False)
class Reference:
    """A print path to track, world frame.

    Attributes
    ----------
    t
        ``(K,)`` sample times (s), ``1 / rate`` apart.
    p
        ``(K, 3)`` nozzle positions (metres).
    v
        ``(K, 3)`` nozzle velocities (m/s).
    extrude
        ``(K,)`` whether the extruder is on.
    length
        Length of the path (metres).
    """

    t: FloatArray
    p: FloatArray
    v: FloatArray
    extrude: NDArray[np.bool_]
    length: float


def print_reference(
    elements: list[Element], speed: float, rate_hz: float = 100.0, max_duration_s: float = 600.0
) -> Reference:
    """The reference path through the print path elements, in their order.

    Parameters
    ----------
    elements
        Print path elements (``polyline`` in the element frame, ``extrude`` flags).
    speed
        Nozzle speed along the path (m/s).
    rate_hz
        Sample rate (Hz).
    max_duration_s
        The longest path accepted (s at ``speed``): the tracking simulation's work bound.

    Raises
    ------
    InputError
        Without print paths, or for a path longer than ``max_duration_s``.
    """
    paths = [e for e in elements if e.type == "print_path" and e.polyline is not None]
    if not paths:
        raise InputError("'fabflow track' follows print paths; the project has none")
    points, flags = [], []
    for e in paths:
        w = apply_T(e.T_world_element, e.polyline)
        ext = np.asarray(e.attributes.get("extrude", np.ones(len(w) - 1)), dtype=bool)
        if points:
            flags.append(False)  # the lift from the previous layer's end
        points.append(w)
        flags.extend(ext.tolist())
    P = np.vstack(points)
    keep = np.r_[True, np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-9]
    seg = np.asarray(flags, dtype=bool)[keep[1:]]
    P = P[keep]
    length = float(np.sum(np.linalg.norm(np.diff(P, axis=0), axis=1)))
    if length / speed > max_duration_s:
        raise InputError(
            f"the print path takes {length / speed:.0f} s at {speed:g} m/s, more than "
            f"tracking.max_duration_s = {max_duration_s:g} s"
        )
    s = sample_hermite(P, speed, rate_hz, seg)
    v = np.gradient(s.points, s.t, axis=0)
    return Reference(t=s.t, p=s.points, v=v, extrude=s.extrude, length=s.length)
