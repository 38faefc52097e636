"""Which turn of A1 each part of a program takes, settled over the whole program.

An arm whose A1 range exceeds a turn (a KUKA KR 60's +-185 deg) reaches a
target straight behind it at A1 = +180 or -180 deg: the same pose, and the
turn decides which way round the arm swings to the next target. The targets
are solved one after the other, each looking one target ahead
(:mod:`fabflow.programs.feasibility`); :func:`settle_a1_turns` then shifts
whole chains (a PTP target and the linear moves after it) by a turn where the
chain stays within the limits, so that the program's PTP moves swing least
(:func:`~fabflow.programs.motion_checks.needless_swings`), then turn A1 least:
dynamic programming over the chains, HOME fixed at both ends.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fabflow.programs.motion_checks import needless_swings
from fabflow.robots.chain import RobotModel

TURNS = np.array([-2.0 * np.pi, 0.0, 2.0 * np.pi])
"""Shifts of A1 (radians) a chain may take."""
SWING_COST = 1e3
"""Cost of one wide swing against A1 travel (radians): any number of radians less."""


def settle_a1_turns(
    robot: RobotModel,
    q: np.ndarray,
    via_q: Sequence[np.ndarray | None],
    ptp: np.ndarray,
    q_home: np.ndarray,
    through_home: np.ndarray,
) -> tuple[np.ndarray, list[np.ndarray | None]]:
    """The joint values with each chain at the turn of A1 the whole program swings least on.

    Parameters
    ----------
    robot
        The robot (A1 about the base z axis).
    q
        ``(n, dof)`` joint values at each target (radians).
    via_q
        Per target, the joint samples inside its linear move (or None).
    ptp
        ``(n,)`` the PTP targets, each starting a chain.
    q_home
        HOME (radians), where the program starts and ends.
    through_home
        ``(n,)`` PTP targets reached through HOME (a configuration change).

    Returns
    -------
    q, via_q
        The same targets, some chains shifted by a turn of A1.
    """
    q = np.array(q, dtype=float)
    n = len(q)
    lo, hi = robot.joint_limits[0]
    if n == 0 or hi - lo <= 2.0 * np.pi:
        return q, list(via_q)
    starts = np.flatnonzero(np.asarray(ptp, dtype=bool))
    starts = np.r_[0, starts[starts > 0]]
    ends = np.r_[starts[1:], n]
    # the A1 range of each chain, its targets and its samples
    sample_lo = np.array([np.inf if v is None else v[:, 0].min() for v in via_q])
    sample_hi = np.array([-np.inf if v is None else v[:, 0].max() for v in via_q])
    a1_lo = np.minimum.reduceat(np.minimum(q[:, 0], sample_lo), starts)
    a1_hi = np.maximum.reduceat(np.maximum(q[:, 0], sample_hi), starts)
    ok = (a1_lo[:, None] + TURNS >= lo - 1e-9) & (a1_hi[:, None] + TURNS <= hi + 1e-9)
    if ok[:, [0, 2]].sum() == 0:
        return q, list(via_q)
    first, last = q[starts], q[ends - 1]
    home = np.asarray(q_home, dtype=float)

    def shifted(x: np.ndarray) -> np.ndarray:
        """(k, 3, dof): each configuration at each turn."""
        out = np.repeat(x[:, None, :], len(TURNS), axis=1)
        out[..., 0] += TURNS
        return out

    def cost(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Cost of the PTP moves ``a`` to ``b`` (broadcast ``(..., dof)``)."""
        a, b = np.broadcast_arrays(a, b)
        flat_a, flat_b = a.reshape(-1, a.shape[-1]), b.reshape(-1, b.shape[-1])
        swing = needless_swings(robot, flat_a, flat_b).reshape(a.shape[:-1])
        return SWING_COST * swing + np.abs(b[..., 0] - a[..., 0])

    F, L = shifted(first), shifted(last)  # (C, 3, dof)
    via = np.asarray(through_home, dtype=bool)[starts]
    # from the end of chain c - 1 (turn i) to the start of chain c (turn j)
    step = cost(L[:-1, :, None, :], F[1:, None, :, :])  # (C - 1, 3, 3)
    homed = cost(L[:-1], home)[:, :, None] + cost(home, F[1:])[:, None, :]
    step = np.where(via[1:, None, None], homed, step)
    total = np.where(ok[0], cost(home, F[0]), np.inf)
    back = np.zeros((len(starts), len(TURNS)), dtype=np.intp)
    for c in range(1, len(starts)):
        options = total[:, None] + step[c - 1]
        back[c] = np.argmin(options, axis=0)
        total = np.where(ok[c], options[back[c], np.arange(len(TURNS))], np.inf)
    total = total + cost(L[-1], home)
    choice = np.empty(len(starts), dtype=np.intp)
    choice[-1] = int(np.argmin(total))
    for c in range(len(starts) - 1, 0, -1):
        choice[c - 1] = back[c, choice[c]]
    shift = np.repeat(TURNS[choice], ends - starts)
    q[:, 0] += shift
    out: list[np.ndarray | None] = []
    for v, s in zip(via_q, shift, strict=True):
        if v is None or s == 0.0:
            out.append(v)
        else:
            v = v.copy()
            v[:, 0] += s
            out.append(v)
    return q, out
