"""The mobile platform carrying an arm: footprint, lift and the arm mounting.

This module owns the platform chain. The arm base sits at

``T_world_base = T_world_platform @ Lift(h) @ T_platform_base``

where ``T_world_platform`` is the platform origin on the ground (z up, x
forward), ``Lift(h)`` raises by ``h`` metres along the platform z axis and
``T_platform_base`` is the arm mounting at the lowest lift position. Every stage
that needs the base pose of a station, the platform pose of a base pose or the
motion of the base when the lift moves calls the functions here. The reach map
of an arm is computed once in the arm base frame; the lift only moves that
frame, which is how :meth:`MobilePlatform.reachable` applies it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.robots.chain import RobotModel
from fabflow.robots.reach import ReachMap
from fabflow.transforms.se3 import inv_T

FloatArray = NDArray[np.float64]


def lift_transform(lift: ArrayLike) -> FloatArray:
    """``Lift(h)``: translation by ``h`` metres along the platform z axis, ``(..., 4, 4)``."""
    h = np.asarray(lift, dtype=float)
    T = np.broadcast_to(np.eye(4), (*h.shape, 4, 4)).copy()
    T[..., 2, 3] = h
    return T


def T_platform_base_at(T_platform_base: ArrayLike, lift: ArrayLike) -> FloatArray:
    """Arm base pose on the platform at lift height(s) ``lift`` (metres)."""
    return lift_transform(lift) @ np.asarray(T_platform_base, dtype=float)


def T_world_base(
    T_world_platform: ArrayLike, lift: ArrayLike, T_platform_base: ArrayLike
) -> FloatArray:
    """Arm base pose(s) in the world: ``T_world_platform @ Lift(lift) @ T_platform_base``.

    Parameters
    ----------
    T_world_platform
        ``(..., 4, 4)`` platform pose(s) on the ground (metres).
    lift
        Lift height(s) (metres), broadcastable with the leading shape of ``T_world_platform``.
    T_platform_base
        4x4 arm mounting on the platform at the lowest lift position.
    """
    return (
        np.asarray(T_world_platform, dtype=float)
        @ lift_transform(lift)
        @ np.asarray(T_platform_base, dtype=float)
    )


def T_world_platform_of(
    T_world_base: ArrayLike, lift: ArrayLike, T_platform_base: ArrayLike
) -> FloatArray:
    """The platform pose under an arm base pose: the inverse of :func:`T_world_base`."""
    return np.asarray(T_world_base, dtype=float) @ inv_T(T_platform_base_at(T_platform_base, lift))


def lift_move(T_platform_base: ArrayLike, lift_from: float, lift_to: float) -> FloatArray:
    """Motion of the arm base, in its own frame, when the lift goes between two heights.

    ``T_world_base(lift_to) = T_world_base(lift_from) @ lift_move(...)``.

    Parameters
    ----------
    T_platform_base
        Arm mounting on the platform at the lowest lift position.
    lift_from, lift_to
        Lift heights (metres along the platform z axis).
    """
    T_pb = np.asarray(T_platform_base, dtype=float)
    return np.linalg.inv(T_pb) @ lift_transform(lift_to - lift_from) @ T_pb


@dataclass(frozen=True, eq=False)
class MobilePlatform:
    """A platform with a lifted arm.

    Attributes
    ----------
    robot
        The arm model.
    footprint
        ``(length, width)`` of the platform rectangle centred on its origin (metres).
    lift_range
        ``(min, max)`` lift height above the lowest position (metres).
    T_platform_base
        4x4 arm mounting pose on the platform at the lowest lift position.
    safety_margin
        Clearance kept around the footprint (metres).
    """

    robot: RobotModel
    footprint: tuple[float, float]
    lift_range: tuple[float, float]
    T_platform_base: FloatArray
    safety_margin: float = 0.0

    def _check_lift(self, lift: float) -> None:
        lo, hi = self.lift_range
        if not lo - 1e-9 <= lift <= hi + 1e-9:
            raise InputError(f"lift {lift:.3f} m is outside the platform's range [{lo}, {hi}] m")

    def T_platform_base_at(self, lift: float) -> FloatArray:
        """Arm base pose on the platform at a lift height (metres)."""
        self._check_lift(lift)
        return T_platform_base_at(self.T_platform_base, lift)

    def T_world_base(self, T_world_platform: ArrayLike, lift: float) -> FloatArray:
        """Arm base pose in the world for a platform pose and lift height."""
        self._check_lift(lift)
        return T_world_base(T_world_platform, lift, self.T_platform_base)

    def footprint_corners(
        self, T_world_platform: ArrayLike, with_margin: bool = True
    ) -> FloatArray:
        """``(4, 2)`` world x, y of the footprint corners (counter-clockwise), with the margin."""
        m = self.safety_margin if with_margin else 0.0
        hx, hy = self.footprint[0] / 2 + m, self.footprint[1] / 2 + m
        c = np.array([[-hx, -hy, 0, 1], [hx, -hy, 0, 1], [hx, hy, 0, 1], [-hx, hy, 0, 1]])
        return (c @ np.asarray(T_world_platform, dtype=float).T)[:, :2]

    def reachable(
        self, reach: ReachMap, p_world: ArrayLike, T_world_platform: ArrayLike, lift: float
    ) -> NDArray[np.bool_]:
        """Which world TCP positions the arm reaches from a platform pose and lift.

        Parameters
        ----------
        reach
            Reach map of the arm and tool (tool orientation as in the map).
        p_world
            ``(N, 3)`` TCP positions in the world (metres).
        T_world_platform
            4x4 platform pose (z = ground, z axis up).
        lift
            Lift height (metres).
        """
        T_world_base = self.T_world_base(T_world_platform, lift)
        p = np.atleast_2d(np.asarray(p_world, dtype=float))
        T_base_world = np.linalg.inv(T_world_base)
        p_base = p @ T_base_world[:3, :3].T + T_base_world[:3, 3]
        return reach.reachable(p_base)

    def reachable_lifts(
        self, reach: ReachMap, p_world: ArrayLike, T_world_platform: ArrayLike, n: int = 25
    ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Reachability of world TCP positions at ``n`` evenly spaced lift heights.

        Returns
        -------
        lifts : numpy.ndarray
            ``(L,)`` lift heights (metres), ascending over the lift range.
        ok : numpy.ndarray
            ``(N, L)`` bool: point i is reachable at lift j.
        """
        lifts = np.linspace(self.lift_range[0], self.lift_range[1], max(n, 1))
        p = np.atleast_2d(np.asarray(p_world, dtype=float))
        T_world_base0 = self.T_world_base(T_world_platform, lifts[0])
        T_base0_world = np.linalg.inv(T_world_base0)
        p_base0 = p @ T_base0_world[:3, :3].T + T_base0_world[:3, 3]
        # Lifting by h raises the base along the platform z axis, which is the base
        # z axis direction expressed in the base frame at the lowest lift.
        up = T_base0_world[:3, :3] @ np.asarray(T_world_platform, dtype=float)[:3, 2]
        shifted = p_base0[:, None, :] - (lifts - lifts[0])[None, :, None] * up
        ok = reach.reachable(shifted.reshape(-1, 3)).reshape(p.shape[0], lifts.size)
        return lifts, ok

    def best_lift(
        self, reach: ReachMap, p_world: ArrayLike, T_world_platform: ArrayLike, n: int = 25
    ) -> tuple[float, int]:
        """The lift (of ``n`` evenly spaced heights) that reaches the most points.

        Returns
        -------
        tuple
            ``(lift, number of reachable points)``; the lowest lift wins ties.
        """
        lifts, ok = self.reachable_lifts(reach, p_world, T_world_platform, n)
        counts = ok.sum(axis=0)
        k = int(np.argmax(counts))
        return float(lifts[k]), int(counts[k])
