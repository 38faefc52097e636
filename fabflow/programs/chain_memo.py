"""Solved chains of a program, kept for the next compile of the same work package.

Collision re-planning (:mod:`fabflow.programs.replan`) compiles a work package
again for every set of routes it tries. Most chains of such a compile (a PTP
target and the linear moves after it, :func:`fabflow.programs.feasibility.solve_moves`)
are those of an earlier one, started from the same configuration. Solving a
chain is deterministic given what :func:`chain_key` holds, so a
:data:`ChainMemo` hands back the earlier solution, to the bit, instead of
solving it again. Its arrays are read-only: programs compiled from one memo
share them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from fabflow.programs.motions import Waypoint

ChainMove = tuple[np.ndarray, float, np.ndarray | None, bool]
"""A linear move of a chain: its joint path (radians), the slowdown of its speed,
the tool poses (world) of a wrist-interpolated move's path (None for the others),
and whether it was made a joint move."""


class ChainSolution(NamedTuple):
    """A solved chain."""

    q: np.ndarray
    """``(dof,)`` configuration at the chain's PTP target (radians)."""
    branch: int
    """The inverse kinematics branch the chain ends on, which the next chain keeps."""
    moves: tuple[ChainMove, ...]
    """Its linear moves in order."""


ChainMemo = dict[tuple[object, ...], ChainSolution]
"""Solved chains of one work package's compiles by :func:`chain_key`."""


def chain_key(
    robot_name: str,
    fixed: np.ndarray,
    q_prev: np.ndarray,
    branch: int,
    samples: np.ndarray,
    counts: np.ndarray,
    waypoints: Sequence[Waypoint],
    whole: np.ndarray,
    ahead: tuple[str, np.ndarray] | None,
) -> tuple[object, ...]:
    """Everything a chain's solution depends on, as a hashable key.

    Parameters
    ----------
    robot_name
        The arm.
    fixed
        The two fixed transforms of the compile, stacked ``(2, 4, 4)``: the world
        in the arm base frame and the flange in the tool frame.
    q_prev, branch
        The configuration (radians) and branch the chain starts from.
    samples
        ``(m, 4, 4)`` tool poses (world) of the chain's targets and the samples of
        its linear moves, in order.
    counts
        Rows of ``samples`` per target.
    waypoints
        The chain's targets (kind, speed, seated, free, element).
    whole
        ``(K,)`` the branches on which the chain's element's whole motion has a
        solution.
    ahead
        What the PTP target looks ahead to: ``("ptp", pose)`` the next PTP
        target's tool pose (world), ``("home", q)`` the joint target after the
        last, or None.
    """
    return (
        robot_name,
        np.ascontiguousarray(fixed, dtype=float).tobytes(),
        np.asarray(q_prev, dtype=float).tobytes(),
        branch,
        np.ascontiguousarray(samples, dtype=float).tobytes(),
        np.asarray(counts, dtype=np.int64).tobytes(),
        tuple((w.kind, w.speed, w.seated, w.free, w.element) for w in waypoints),
        np.asarray(whole, dtype=bool).tobytes(),
        None if ahead is None else (ahead[0], np.asarray(ahead[1], dtype=float).tobytes()),
    )


def frozen(q: np.ndarray, branch: int, moves: Sequence[ChainMove]) -> ChainSolution:
    """A chain's solution with its arrays made read-only, to be shared."""
    q = np.array(q, dtype=float)
    q.setflags(write=False)
    for path, _, samples, _ in moves:
        path.setflags(write=False)
        if samples is not None:
            samples.setflags(write=False)
    return ChainSolution(q, branch, tuple(moves))
