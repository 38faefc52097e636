"""The planner's reach model: a fine (r, z) table of where the arm reaches, tool down.

An arm whose first axis is vertical and turns (almost) a full circle reaches
the same set in every direction, so reachability with the tool pointing down
(any rotation about the tool axis) depends only on the horizontal distance
``r`` of the TCP from the base axis and its height ``z`` above the base. The
model is a boolean table over a regular (r, z) grid, built once per robot and
tool and cached:

* from the inverse-kinematics reach map of :func:`fabflow.robots.reach.reach_map`,
  sampled at the table's cell centres (``source = "ik"``, the planner's model);
* or, on request or when the arm has no reach map, from the catalogue geometry
  alone (``source = "geometric"``): the wrist centre, ``d6 + tool offset`` above
  the TCP, must lie in the annulus the shoulder and elbow links sweep (shrunk by
  a small margin), and the forearm may rise at most ``A5_max - 90 deg`` above
  horizontal so the wrist can still turn the tool straight down; targets closer
  than 0.6 m to axis 1 are left out. Joint limits of A2 and A3 and the tool's
  sideways offset are not modelled by this approximation. The dimensions are
  read from the robot's DH table, for arms with an offset shoulder and a
  spherical wrist (the KUKA and ABB arms of the catalogue).

The table is eroded by one cell, so a grid lookup errs on the unreachable side.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from fabflow.errors import UnsupportedError
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.robots.reach import reach_map

SPHERICAL_WRIST_ALPHAS = (-math.pi / 2, 0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, 0.0)
"""DH twists of a six-axis arm with an offset shoulder and a spherical wrist."""

R_STEP = 0.02
Z_STEP = 0.02
R_MAX_TABLE = 3.5
Z_MIN_TABLE = -3.0
Z_MAX_TABLE = 4.0
R_MIN_FALLBACK = 0.6
"""The fallback ignores targets closer to axis 1 than this (metres): folding that
tight hits the A2/A3 limits or the arm itself."""
ANNULUS_MARGIN = 0.02
"""Fraction by which the fallback shrinks the link annulus (keeps away from full stretch)."""


@dataclass(frozen=True, eq=False)
class ReachModel:
    """Tool-down reachability over (r, z) in the arm base frame.

    Attributes
    ----------
    table
        (nr, nz) bool; cell (i, j) covers r in [i, i+1) * r_step and
        z in z_min + [j, j+1) * z_step (metres).
    r_step, z_step, z_min
        Grid spacing and origin (metres).
    source
        ``"ik"`` (sampled from the reach map) or ``"geometric"`` (from the DH table).
    robot
        Robot model name.
    """

    table: np.ndarray
    r_step: float
    z_step: float
    z_min: float
    source: str
    robot: str

    @functools.cached_property
    def r_max(self) -> float:
        """Largest horizontal TCP distance from the base axis that is reachable (metres)."""
        rows = np.flatnonzero(self.table.any(axis=1))
        return 0.0 if len(rows) == 0 else float((rows[-1] + 1) * self.r_step)

    @functools.cached_property
    def z_range(self) -> tuple[float, float]:
        """Lowest and highest reachable TCP height above the base (metres)."""
        cols = np.flatnonzero(self.table.any(axis=0))
        if len(cols) == 0:
            return (0.0, 0.0)
        return (self.z_min + cols[0] * self.z_step, self.z_min + (cols[-1] + 1) * self.z_step)

    def reachable(self, r: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Whether TCP positions are reachable with the tool pointing down.

        Parameters
        ----------
        r
            Horizontal distances from the base axis (metres), any shape.
        z
            Heights above the base frame origin (metres), broadcastable with ``r``.

        Returns
        -------
        np.ndarray
            Boolean array of the broadcast shape.
        """
        return self._padded[self._r_index(r), self._z_index(z)]

    def level_masks(self, r: np.ndarray, frame: np.ndarray, z: np.ndarray) -> np.ndarray:
        """:meth:`reachable` of many points at a few heights each, as bit masks.

        Parameters
        ----------
        r
            ``(P,)`` horizontal distances from the base axis (metres).
        frame
            ``(P,)`` row of ``z`` of each point.
        z
            ``(K, L)`` heights above the base frame origin (metres), ``L <= 63``:
            per row, the heights each point of that row is looked at.

        Returns
        -------
        numpy.ndarray
            ``(P,)`` int64: bit ``l`` set where point ``p`` is reachable at
            height ``z[frame[p], l]``.

        The heights' table columns are found once per row of ``z``, and the
        masks once per row and distance cell, not per point.
        """
        z = np.asarray(z, dtype=float)
        j = self._z_index(z)  # (K, L)
        masks = np.zeros((self._padded.shape[0], len(z)), dtype=np.int64)  # (r cells, K)
        for level in range(z.shape[1]):
            masks |= self._padded[:, j[:, level]].astype(np.int64) << level
        return masks[self._r_index(r), np.asarray(frame, dtype=np.intp)]

    def _r_index(self, r: np.ndarray) -> np.ndarray:
        """Row of the padded table (:attr:`_padded`) of each distance; outside: its border."""
        r = np.asarray(r, dtype=float)
        n = self._padded.shape[0]
        return np.clip(np.floor(r * (1.0 / self.r_step)), -1, n - 2).astype(np.intp) + 1

    def _z_index(self, z: np.ndarray) -> np.ndarray:
        """Column of the padded table of each height; outside: its border."""
        z = np.asarray(z, dtype=float)
        n = self._padded.shape[1]
        return (
            np.clip(np.floor((z - self.z_min) * (1.0 / self.z_step)), -1, n - 2).astype(np.intp) + 1
        )

    @functools.cached_property
    def _padded(self) -> np.ndarray:
        return np.pad(self.table, 1, constant_values=False)

    def shrunk(self, margin: float) -> ReachModel:
        """The model with the reachable set eroded by ``margin`` metres in r and z.

        Planning with a shrunk model keeps every target at least ``margin`` inside
        the reachable set, so parking and localization errors of that size stay
        within reach.
        """
        cells = math.ceil(margin / min(self.r_step, self.z_step) - 1e-9)
        if cells <= 0:
            return self
        # Erosion by the disk of radius ``margin``: a cell stays when no unreachable cell
        # (nor the outside, one padded cell) lies within ``margin`` of it. The distance
        # transform does it in one pass whatever the margin (a disk structure grows
        # with the square of the margin).
        padded = np.pad(self.table, 1, constant_values=False)
        d = ndimage.distance_transform_edt(padded, sampling=(self.r_step, self.z_step))
        table = (d[1:-1, 1:-1] ** 2 > margin**2 + 1e-12) & self.table
        return ReachModel(
            table=table,
            r_step=self.r_step,
            z_step=self.z_step,
            z_min=self.z_min,
            source=self.source,
            robot=self.robot,
        )

    def reachable_base(self, p_base: np.ndarray) -> np.ndarray:
        """Whether TCP positions (N, 3) in the base frame are reachable, tool pointing down."""
        p = np.asarray(p_base, dtype=float).reshape(-1, 3)
        return self.reachable(np.hypot(p[:, 0], p[:, 1]), p[:, 2])


def _grid() -> tuple[np.ndarray, np.ndarray]:
    r = (np.arange(round(R_MAX_TABLE / R_STEP)) + 0.5) * R_STEP
    z = Z_MIN_TABLE + (np.arange(round((Z_MAX_TABLE - Z_MIN_TABLE) / Z_STEP)) + 0.5) * Z_STEP
    return r, z


def arm_dimensions(robot: RobotModel) -> dict[str, float]:
    """DH ``d1, a1, a2, a3, d4, d6`` (metres) and the A5 limit (``a5_max_deg``) of an arm.

    Raises
    ------
    UnsupportedError
        When the arm has no offset shoulder and spherical wrist in the DH sense.
    """
    dh = robot.dh
    if dh is None or robot.dof != 6 or not np.allclose(dh[:, 1], SPHERICAL_WRIST_ALPHAS, atol=1e-9):
        raise UnsupportedError(
            f"no reach model for robot '{robot.name}': it needs closed-form IK (an OPW arm) "
            "or a DH table of a six-axis arm with an offset shoulder and a spherical wrist"
        )
    return {
        "d1": float(dh[0, 2]),
        "a1": float(dh[0, 0]),
        "a2": float(dh[1, 0]),
        "a3": float(dh[2, 0]),
        "d4": float(dh[3, 2]),
        "d6": float(dh[5, 2]),
        "a5_max_deg": float(np.degrees(robot.joint_limits[4, 1])),
    }


def geometric_table(robot: str, tool_offset: float) -> np.ndarray:
    """Reach table from the catalogue geometry alone (see the module docstring).

    Parameters
    ----------
    robot
        Robot model name; an arm accepted by :func:`arm_dimensions`.
    tool_offset
        Distance from the flange to the TCP along the flange z axis (metres).

    Returns
    -------
    np.ndarray
        (nr, nz) bool table on the grid of :class:`ReachModel` (cell centres), not eroded.
    """
    g = arm_dimensions(get_robot(robot))
    r, z = _grid()
    R, Z = np.meshgrid(r, z, indexing="ij")
    dx = R - g["a1"]
    dz = Z + g["d6"] + tool_offset - g["d1"]
    L2 = g["a2"]
    L3 = math.hypot(g["a3"], g["d4"])
    D = np.hypot(dx, dz)
    ok_len = (D <= (L2 + L3) * (1.0 - ANNULUS_MARGIN)) & (
        D >= abs(L2 - L3) + ANNULUS_MARGIN * (L2 + L3)
    )
    phi = np.arctan2(dz, dx)
    cos_beta = np.clip((L2**2 + D**2 - L3**2) / (2.0 * L2 * np.maximum(D, 1e-9)), -1.0, 1.0)
    beta = np.arccos(cos_beta)
    max_rise = math.radians(g["a5_max_deg"] - 90.0)
    ok_wrist = np.zeros_like(ok_len)
    for sign in (1.0, -1.0):
        theta2 = phi + sign * beta
        fx = dx - L2 * np.cos(theta2)
        fz = dz - L2 * np.sin(theta2)
        ok_wrist |= np.arctan2(fz, np.abs(fx)) <= max_rise
    return ok_len & ok_wrist & (R >= R_MIN_FALLBACK)


def _ik_table(robot: str, T_flange_tool: np.ndarray) -> np.ndarray | None:
    try:
        rm = reach_map(robot, T_flange_tool, tool_axis="down")
    except UnsupportedError:
        return None
    r, z = _grid()
    R, Z = np.meshgrid(r, z, indexing="ij")
    p = np.stack([R.ravel(), np.zeros(R.size), Z.ravel()], axis=1)
    return np.asarray(rm.reachable(p), dtype=bool).reshape(R.shape)


@functools.lru_cache(maxsize=16)
def _cached_model(robot: str, T_key: tuple[float, ...], use_ik: bool) -> ReachModel:
    T_flange_tool = np.asarray(T_key, dtype=float).reshape(4, 4)
    table = _ik_table(robot, T_flange_tool) if use_ik else None
    source = "ik"
    if table is None:
        table = geometric_table(robot, float(T_flange_tool[2, 3]))
        source = "geometric"
    table = ndimage.binary_erosion(table, structure=np.ones((3, 3), dtype=bool), border_value=0)
    return ReachModel(
        table=table, r_step=R_STEP, z_step=Z_STEP, z_min=Z_MIN_TABLE, source=source, robot=robot
    )


def reach_model(robot: str, T_flange_tool: np.ndarray, use_ik: bool = True) -> ReachModel:
    """The (cached) reach model of a robot with a tool.

    Parameters
    ----------
    robot
        Robot model name (``"kuka_kr60_3"``, ...).
    T_flange_tool
        4x4 TCP pose in the flange frame (metres).
    use_ik
        Sample the table from the arm's inverse-kinematics reach map when it has
        one; ``False`` forces the geometric approximation.
    """
    key = tuple(np.round(np.asarray(T_flange_tool, dtype=float).ravel(), 9).tolist())
    return _cached_model(robot, key, use_ik)
