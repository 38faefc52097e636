"""Joint values on a configuration boundary, read the same way whatever their float noise.

Controllers describe a configuration with bits taken from joint signs (KUKA's
Turn, the sign of A5 in KUKA's Status and ABB's ``cfx``) and quadrants (ABB's
``cf1``, ``cf4``, ``cf6``). A joint that sits exactly on such a boundary — A1 at 0
when the magazine lies straight ahead of the arm — comes out of inverse
kinematics as ``±1e-16``, so the bit would follow the rounding of the solve and a
program would change when nothing moved. Values within :data:`BOUNDARY_TOL_RAD`
of a boundary are set onto it before the bits are taken.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

BOUNDARY_TOL_RAD = 1e-9
"""How close (radians) a joint value must be to a boundary to be read as on it.

Far below what a controller resolves (about 1e-6 rad per encoder count) and
far above the 1e-15 rad rounding of an inverse-kinematics solve.
"""


def settle_zeros(q: ArrayLike) -> NDArray[np.float64]:
    """Joint values with those within :data:`BOUNDARY_TOL_RAD` of 0 set to ``+0.0``.

    Parameters
    ----------
    q
        Joint values in radians, any shape.

    Returns
    -------
    numpy.ndarray
        A float copy of ``q``; signs read from it (``< 0``, ``<= 0``) no longer
        depend on rounding.
    """
    q = np.array(q, dtype=float)
    q[np.abs(q) <= BOUNDARY_TOL_RAD] = 0.0
    return q


def quadrants(q: ArrayLike, step: float = np.pi / 2) -> NDArray[np.int64]:
    """``floor(q / step)`` with values within :data:`BOUNDARY_TOL_RAD` of a boundary on it.

    Parameters
    ----------
    q
        Joint values in radians, any shape.
    step
        Width of a quadrant in radians (ABB: 90 deg).

    Returns
    -------
    numpy.ndarray
        Integer quadrants, the shape of ``q``: a value just below ``k * step``
        (by rounding) counts as ``k`` like the value ``k * step`` itself.

    Raises
    ------
    ValueError
        For a value that is not finite (it has no quadrant).
    """
    t = np.asarray(q, dtype=float) / step
    if not np.isfinite(t).all():
        raise ValueError("quadrants of joint values that are not finite")
    k = np.round(t)
    t = np.where(np.abs(t - k) * step <= BOUNDARY_TOL_RAD, k, t)
    return np.floor(t).astype(np.int64)
