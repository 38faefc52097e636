"""Drawing a robot arm from its kinematic model (:mod:`fabflow.robots`)."""

from __future__ import annotations

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
        d = self.model.dh[:, 2]
        dof = self.model.dof
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
