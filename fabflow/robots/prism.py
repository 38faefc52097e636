"""Where a robot can hold a prism, and where the prism is: reach test and forward kinematics.

Total station localization moves a 360-degree prism on the tool to points of
the robot base frame and needs each one reached and then placed exactly by
forward kinematics. Arms with closed-form inverse kinematics reach a point with
the tool pointing down (as in the reach maps of :mod:`fabflow.robots.reach`).
Machines without one (the 5-DOF BROKK) cannot choose the tool orientation, and
a 360-degree prism does not need it: their reachable prism positions are a
dense cloud of forward-kinematics samples of the joint space, and a point is
reached by the nearest sample.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from fabflow.errors import InputError, LocalizationError
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.transforms.se3 import inv_T, make_T
from fabflow.transforms.so3 import R_FLIP_X

SAMPLE_TOLERANCE = 0.03
"""Largest distance (m) to a sampled prism position that counts as reachable (no closed-form IK)."""

N_SAMPLES = 40000
"""Joint-space samples of a machine without closed-form IK (seeded, so always the same)."""


@dataclass(frozen=True, eq=False)
class PrismReach:
    """Reach test and prism placement for one robot and tool (prism at the TCP).

    Attributes
    ----------
    robot
        The machine.
    T_flange_tool
        4x4 prism (TCP) pose in the flange frame (metres).
    samples_q, samples_tree
        For a machine without closed-form IK: joint samples and a k-d tree of
        their prism positions (base frame); ``None`` otherwise.
    """

    robot: RobotModel
    T_flange_tool: np.ndarray
    samples_q: np.ndarray | None = None
    samples_tree: cKDTree | None = None

    def reachable(self, points: np.ndarray) -> np.ndarray:
        """Whether the prism reaches ``(n, 3)`` base-frame points (metres), ``(n,)`` bool."""
        if self.samples_tree is not None:
            d, _ = self.samples_tree.query(points)
            return d <= SAMPLE_TOLERANCE
        T = _tool_down(points)
        _, valid = self.robot.ik_batch(T @ inv_T(self.T_flange_tool))
        return valid.any(axis=1)

    def prism_points(self, points: np.ndarray) -> np.ndarray:
        """Joint values for the desired ``(n, 3)`` points, then the prism positions by FK.

        Raises
        ------
        LocalizationError
            When a point is out of reach.
        """
        if self.samples_tree is not None and self.samples_q is not None:
            d, k = self.samples_tree.query(points)
            bad = d > SAMPLE_TOLERANCE
            q = self.samples_q[k]
        else:
            T_base_flange = _tool_down(points) @ inv_T(self.T_flange_tool)
            q, valid = self.robot.ik_batch(T_base_flange)
            bad = ~valid.any(axis=1)
            q = q[np.arange(len(points)), np.argmax(valid, axis=1)]
        if bad.any():
            p = points[int(np.argmax(bad))]
            raise LocalizationError(
                f"{self.robot.name} cannot reach the localization point "
                f"({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f})"
            )
        return (self.robot.fk(q) @ self.T_flange_tool)[:, :3, 3]


def _tool_down(points: np.ndarray) -> np.ndarray:
    """Tool poses at ``points`` with the tool z axis pointing down (base frame)."""
    return make_T(np.broadcast_to(R_FLIP_X, (len(points), 3, 3)), points)


def prism_reach(model: str, T_flange_tool: np.ndarray) -> PrismReach:
    """The :class:`PrismReach` of a catalogue robot with its prism at ``T_flange_tool``."""
    robot = get_robot(model)
    if robot.analytic_ik is not None:
        return PrismReach(robot, T_flange_tool)
    q, tree = _joint_samples(model, tuple(np.asarray(T_flange_tool, float).ravel()))
    return PrismReach(robot, T_flange_tool, q, tree)


@functools.lru_cache(maxsize=16)
def _joint_samples(model: str, T_flange_tool: tuple[float, ...]) -> tuple[np.ndarray, cKDTree]:
    robot = get_robot(model)
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    q = np.random.default_rng(0).uniform(lo, hi, (N_SAMPLES, robot.dof))
    p = (robot.fk(q) @ np.asarray(T_flange_tool).reshape(4, 4))[:, :3, 3]
    return q, cKDTree(p)


def prism_points_from_joints(
    model: str,
    joints: np.ndarray,
    T_flange_prism: np.ndarray,
    source: str | None = None,
    lines: Sequence[int] = (),
) -> np.ndarray:
    """Prism positions ``(n, 3)`` in the base frame from joint values ``(n, dof)`` (radians).

    Raises
    ------
    InputError
        When the number of joints does not match the robot or a configuration
        lies outside the joint limits (the robot cannot have stood there).
    """
    rob = get_robot(model)
    q = np.asarray(joints, dtype=float)
    if q.shape[1] != rob.dof:
        raise InputError(
            f"{model} has {rob.dof} joints but the file gives {q.shape[1]} (q1_deg..)", source
        )
    ok = rob.within_limits(q)
    if not ok.all():
        k = int(np.argmin(ok))
        where = f"line {lines[k]}" if lines else None
        raise InputError(f"joint values outside the limits of {model}", source, where)
    return (rob.fk(q) @ np.asarray(T_flange_prism, dtype=float))[:, :3, 3]
