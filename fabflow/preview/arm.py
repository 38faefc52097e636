"""The arm in the preview: drawing it from its kinematic model, and its pose at every step."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from fabflow.robots.chain import RobotModel


class RobotArm:
    """A :class:`~fabflow.robots.chain.RobotModel` as the preview draws it.

    The arm is drawn as a polyline through, for each DH link ``i``, the origin of
    frame ``i - 1``, that point moved by ``d_i`` along its z axis, and the
    origin of frame ``i``, so offsets such as the KR 60-3's 0.35 m shoulder
    read as an L instead of a diagonal; then the flange and the tool centre
    point. Zero-length pieces are drawn with zero radius.

    Parameters
    ----------
    model
        The machine model.
    T_flange_tool
        4x4 tool centre point in the flange frame (metres).
    home
        Home configuration (radians); the model's ``home`` if it has one, else
        the zero configuration clipped to the joint limits.
    """

    def __init__(
        self,
        model: RobotModel,
        T_flange_tool: np.ndarray | None = None,
        home: np.ndarray | None = None,
    ) -> None:
        self.model = model
        self.name = model.name
        self.T_flange_tool = np.eye(4) if T_flange_tool is None else np.asarray(T_flange_tool)
        if home is None:
            home = getattr(model, "home", None)
        if home is None:
            lo, hi = model.joint_limits[:, 0], model.joint_limits[:, 1]
            home = np.clip(np.zeros(model.dof), lo, hi)
        self.home = np.asarray(home, dtype=float)

    def joint_origins(self, q: np.ndarray) -> np.ndarray:
        """Drawing points in the base frame, shape ``(..., 2 * dof + 3, 3)`` (metres)."""
        F = np.asarray(self.model.frames(q), dtype=float)
        dof = self.model.dof
        d = self.model.dh[:, 2] if self.model.dh is not None else np.zeros(dof)
        origins = F[..., : dof + 1, :3, 3]
        mids = origins[..., :dof, :] + d[:, None] * F[..., :dof, :3, 2]
        pts = np.empty((*F.shape[:-3], 2 * dof + 3, 3))
        pts[..., 0, :] = origins[..., 0, :]
        pts[..., 1 : 2 * dof : 2, :] = mids
        pts[..., 2 : 2 * dof + 1 : 2, :] = origins[..., 1:, :]
        T_flange = F[..., -1, :, :]
        pts[..., 2 * dof + 1, :] = T_flange[..., :3, 3]
        pts[..., 2 * dof + 2, :] = (T_flange @ self.T_flange_tool)[..., :3, 3]
        return pts

    def fk(self, q: np.ndarray) -> np.ndarray:
        """Flange pose in the base frame (4x4, metres)."""
        return self.model.fk(q)

    def ik(self, T_base_flange: np.ndarray) -> list[np.ndarray]:
        """All joint solutions within limits for a flange pose in the base frame."""
        return self.model.ik(T_base_flange)

    def ik_many(self, T_base_flange: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Closed-form IK for (N, 4, 4) poses: ``(q (N, K, dof), valid (N, K))``.

        ``None`` when the model has no closed-form solver.
        """
        if self.model.analytic_ik is None:
            return None
        return self.model.ik_batch(T_base_flange)


class ArmModel(Protocol):
    """What the preview needs of a robot arm.

    ``joint_origins`` returns the points the arm is drawn through (foot of axis
    1, each joint origin, the flange) in the robot base frame, shape
    ``(..., n_points, 3)`` for joint vectors of shape ``(..., dof)``; ``fk``
    the flange pose in the base frame (4x4).
    ``ik`` returns the joint solutions (radians) that put the flange at a 4x4
    pose given in the base frame, empty when unreachable. An arm may also offer
    ``ik_many(T (N, 4, 4)) -> (q (N, K, dof), valid (N, K)) | None`` to solve
    all targets at once.
    """

    name: str
    home: np.ndarray

    def joint_origins(self, q: np.ndarray) -> np.ndarray: ...

    def fk(self, q: np.ndarray) -> np.ndarray: ...

    def ik(self, T_base_flange: np.ndarray) -> list[np.ndarray]: ...


def _choose_solution(solutions: Sequence[np.ndarray], reference: np.ndarray) -> np.ndarray | None:
    """The IK solution closest (in joint space) to ``reference``."""
    if not solutions:
        return None
    sols = np.asarray(solutions, dtype=float).reshape(len(solutions), -1)
    return sols[int(np.argmin(np.linalg.norm(sols - reference, axis=1)))]


def _arm_configurations(
    arm: ArmModel,
    T_world_base_p: np.ndarray,
    step_package: np.ndarray,
    T_world_targets: np.ndarray,
    T_flange_tool: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Joint configuration per step (home at step 0) and whether the target was reached.

    At each step the IK solution closest to the previous step's configuration
    is drawn, so the arm moves smoothly; an unreachable target keeps the
    previous configuration and is flagged.
    """
    S = T_world_targets.shape[0]
    home = np.asarray(arm.home, dtype=float)
    q = np.empty((S + 1, home.shape[0]))
    reached = np.ones(S + 1, dtype=bool)
    q[0] = home
    if S == 0:
        return q, reached
    T_base_world = np.linalg.inv(T_world_base_p)[step_package]
    T_tool_flange = np.linalg.inv(T_flange_tool)
    T_base_flange = T_base_world @ T_world_targets @ T_tool_flange
    ik_many = getattr(arm, "ik_many", None)
    batch = ik_many(T_base_flange) if ik_many is not None else None
    for k in range(S):
        if batch is not None:
            sols = list(batch[0][k][batch[1][k]])
        else:
            sols = arm.ik(T_base_flange[k])
        sol = _choose_solution(sols, q[k])
        if sol is None:
            q[k + 1] = q[k]
            reached[k + 1] = False
        else:
            q[k + 1] = sol
    return q, reached


def arm_track(
    arm: ArmModel | None,
    T_wb: np.ndarray,
    step_package: np.ndarray,
    T_world_targets: np.ndarray,
    T_flange_tool: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The arm at the start and at every step: joints, reached, joint origins, tool pose.

    Returns
    -------
    arm_q
        (S + 1, dof) joint values (``dof`` 0 without an arm).
    reached
        (S + 1,) whether the arm reaches the step's target.
    arm_points
        (S + 1, J, 3) joint origins in the world (metres).
    T_world_tool
        (S + 1, 4, 4) tool poses: the arm's home tool pose, then the targets.
    """
    S, P = len(step_package), len(T_wb)
    if arm is not None and P > 0:
        arm_q, reached = _arm_configurations(
            arm, T_wb, step_package, T_world_targets, T_flange_tool
        )
        pts_base = np.asarray(arm.joint_origins(arm_q), dtype=float)
        pkg_of_step = np.concatenate([[0], step_package])
        T = T_wb[pkg_of_step]
        arm_points = np.einsum("sij,snj->sni", T[:, :3, :3], pts_base) + T[:, None, :3, 3]
        T_world_tool = np.array([T_wb[0]] * (S + 1))
        T_world_tool[1:] = T_world_targets
        T_world_tool[0] = T_wb[0] @ np.asarray(arm.fk(arm_q[0]), dtype=float) @ T_flange_tool
    else:
        arm_q = np.zeros((S + 1, 0))
        reached = np.ones(S + 1, dtype=bool)
        arm_points = np.zeros((S + 1, 0, 3))
        T_world_tool = np.zeros((S + 1, 4, 4))
        T_world_tool[0] = T_wb[0] if P else np.eye(4)
        T_world_tool[1:] = T_world_targets
    return arm_q, reached, arm_points, T_world_tool
