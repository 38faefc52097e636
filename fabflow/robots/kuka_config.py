"""KUKA Status and Turn (S, T) of a KR 60-3 configuration, KSS conventions.

Status S (3 bits):

* bit 0 - 1 when the wrist root point (intersection of A4, A5, A6) has a
  negative x in the A1 coordinate system (the frame of $ROBROOT turned with A1):
  the "overhead" area; 0 in the basic area.
* bit 1 - 1 when A3 >= phi, phi being the A3 angle at which the wrist root point
  lies on the line through A2 and A3 (for the KR 60-3, with its 145 mm forearm
  offset, phi = atan(0.145 / 0.820) = 10.03 deg); 0 below it.
* bit 2 - 1 when A5 <= 0, 0 when A5 > 0.

Turn T (6 bits): bit i is 1 when axis A(i+1) is negative.

The KUKA home pose A1..A6 = (0, -90, 90, 0, 10, 0) deg gives S = 2, T = 2.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.robots.catalog import KR60_3_OPW, get_robot

KR60_3_PHI = float(np.arctan2(-KR60_3_OPW.a2, KR60_3_OPW.c3))
"""A3 angle (radians) at which the KR 60-3 wrist root point is in line with A2 and A3."""


def kuka_status_turn(q: ArrayLike) -> tuple[int, int] | tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Status and Turn of KR 60-3 joint values.

    Parameters
    ----------
    q
        A1..A6 in radians, shape ``(6,)`` or ``(N, 6)``.

    Returns
    -------
    tuple
        ``(S, T)`` as Python ints for one configuration, or two ``(N,)`` integer
        arrays for a batch.
    """
    robot = get_robot("kuka_kr60_3")
    qb, single = robot._as_batch(q)
    T_base_flange = robot.fk(qb)
    wrist = T_base_flange[:, :3, 3] - KR60_3_OPW.c4 * T_base_flange[:, :3, 2]
    # A1 turns the arm about -z, so the A1 frame's x axis is (cos A1, -sin A1, 0).
    x_a1 = wrist[:, 0] * np.cos(qb[:, 0]) - wrist[:, 1] * np.sin(qb[:, 0])
    bit0 = (x_a1 < 0).astype(np.int64)
    bit1 = (qb[:, 2] >= KR60_3_PHI).astype(np.int64)
    bit2 = (qb[:, 4] <= 0).astype(np.int64)
    S = bit0 | (bit1 << 1) | (bit2 << 2)
    turn = (qb < 0).astype(np.int64) << np.arange(6)
    T = turn.sum(axis=1)
    if single:
        return int(S[0]), int(T[0])
    return S, T
