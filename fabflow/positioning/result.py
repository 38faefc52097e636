"""The localization result every method returns: the robot base pose with its uncertainty.

Covariance convention (shared by all of fabflow): a 6x6 matrix over the error
vector ``[dx, dy, dz, rx, ry, rz]`` where the true pose is
``T = [Exp([rx, ry, rz]) @ R_est, t_est + [dx, dy, dz]]``: translation error in
metres and a small rotation in radians, both expressed in the parent frame
(world for ``T_world_base``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fabflow.output import write_json
from fabflow.positioning.integrity import Integrity


@dataclass(frozen=True, eq=False)
class BasePose:
    """A localized robot base pose.

    Attributes
    ----------
    T_world_base
        4x4 pose of the robot base in the world frame (metres).
    covariance
        6x6 covariance of ``[dx, dy, dz, rx, ry, rz]`` (m^2, rad^2; see module docstring).
    method
        ``"uwb"``, ``"total_station"`` or ``"icp"`` (with a detail such as the estimator
        in ``quality``).
    residuals
        Per-measurement residuals (n x k, metres), as the method defines them.
    rmse
        Root mean square of the residuals (metres).
    station
        The station id this result belongs to, if any.
    quality
        Further quality figures: number of measurements/inliers, fitness, outliers, ...
    integrity
        The statistical tests of the pose and their outcome
        (:class:`~fabflow.positioning.integrity.Integrity`); ``None`` only for a
        result built by hand, which the localization stage treats as untested.
    """

    T_world_base: np.ndarray
    covariance: np.ndarray
    method: str
    residuals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rmse: float = 0.0
    station: str | None = None
    quality: dict[str, Any] = field(default_factory=dict)
    integrity: Integrity | None = None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible data (the base pose JSON schema of ``fabflow localize``)."""
        return {
            "method": self.method,
            "station": self.station,
            "T_world_base": np.asarray(self.T_world_base, dtype=float).tolist(),
            "covariance": np.asarray(self.covariance, dtype=float).tolist(),
            "residuals": np.asarray(self.residuals, dtype=float).tolist(),
            "rmse": float(self.rmse),
            "quality": self.quality,
            "integrity": None if self.integrity is None else self.integrity.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BasePose:
        """Inverse of :meth:`to_dict`."""
        res = np.asarray(d.get("residuals", []), dtype=float)
        return cls(
            T_world_base=np.asarray(d["T_world_base"], dtype=float).reshape(4, 4),
            covariance=np.asarray(d["covariance"], dtype=float).reshape(6, 6),
            method=str(d["method"]),
            residuals=res,
            rmse=float(d.get("rmse", 0.0)),
            station=d.get("station"),
            quality=dict(d.get("quality", {})),
            integrity=None if d.get("integrity") is None else Integrity.from_dict(d["integrity"]),
        )

    def write(self, path: str | Path) -> Path:
        """Write the result as JSON to ``path``."""
        return write_json(path, self.to_dict())
