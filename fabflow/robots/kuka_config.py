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

An axis within float noise of 0 counts as 0 for bit 2 and the turn bits
(:mod:`fabflow.robots.joint_boundaries`): A1 straight ahead gives the same
bits however the solve rounded it.

The KUKA home pose A1..A6 = (0, -90, 90, 0, 10, 0) deg gives S = 2, T = 2.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import UnsupportedError
from fabflow.robots.catalog import KR60_3_OPW, get_robot
from fabflow.robots.chain import RobotModel
from fabflow.robots.joint_boundaries import settle_zeros

KR60_3_PHI = float(np.arctan2(-KR60_3_OPW.a2, KR60_3_OPW.c3))
"""A3 angle (radians) at which the KR 60-3 wrist root point is in line with A2 and A3."""


def kuka_status_turn(
    q: ArrayLike, robot: RobotModel | None = None
) -> tuple[int, int] | tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Status and Turn of KUKA joint values.

    Parameters
    ----------
    q
        A1..A6 in radians, shape ``(6,)`` or ``(N, 6)``.
    robot
        The arm (default the KR 60-3): a six-axis arm with an ortho-parallel
        geometry (``RobotModel.opw``), whose forearm offset sets the A3 angle of
        bit 1 and whose wrist centre (``c4`` behind the last joint frame) bit 0.

    Returns
    -------
    tuple
        ``(S, T)`` as Python ints for one configuration, or two ``(N,)`` integer
        arrays for a batch.

    Raises
    ------
    UnsupportedError
        For an arm without an ortho-parallel geometry (KRL's status bits are not
        defined for it).
    """
    robot = get_robot("kuka_kr60_3") if robot is None else robot
    p = robot.opw
    if p is None or robot.dof != 6:
        raise UnsupportedError(
            f"KUKA status and turn need a six-axis arm with an ortho-parallel geometry "
            f"(OPW); {robot.name} has none: define it with 'opw' (or an OPW DH table), "
            "or write JSON programs"
        )
    phi = float(np.arctan2(-p.a2, p.c3))
    qb, single = robot._as_batch(q)
    T_base_last = robot.frames(qb)[:, robot.dof]
    wrist = T_base_last[:, :3, 3] - p.c4 * T_base_last[:, :3, 2]
    # The A1 frame's x axis is (cos t1, sin t1, 0) with t1 the OPW angle of axis 1
    # (the KR 60-3's A1 turns the arm about -z: t1 = -A1).
    t1 = p.signs[0] * qb[:, 0] - p.offsets[0]
    x_a1 = wrist[:, 0] * np.cos(t1) + wrist[:, 1] * np.sin(t1)
    bit0 = (x_a1 < 0).astype(np.int64)
    bit1 = (p.signs[2] * qb[:, 2] - p.offsets[2] >= phi).astype(np.int64)
    signs = settle_zeros(qb)
    bit2 = (signs[:, 4] <= 0).astype(np.int64)
    S = bit0 | (bit1 << 1) | (bit2 << 2)
    turn = (signs < 0).astype(np.int64) << np.arange(6)
    T = turn.sum(axis=1)
    if single:
        return int(S[0]), int(T[0])
    return S, T
