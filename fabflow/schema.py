"""Building blocks of the project schema, shared by every section.

:class:`StrictModel` is the base of every model of the project file (unknown
keys are errors, models are frozen); :class:`PoseSpec` is how a project file
writes a rigid pose; the annotated types carry the units and bounds the fields
share. The sections themselves live with the room that owns them
(:mod:`fabflow.design.specs` for what to build) and are put together in
:mod:`fabflow.project`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationInfo

from fabflow.transforms.so3 import matrix_from_abc


class StrictModel(BaseModel):
    """Base of every project model: unknown keys are errors, values are not coerced."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def _resolve_path(value: Path, info: ValidationInfo) -> Path:
    base = (info.context or {}).get("base_dir")
    path = Path(value).expanduser()
    if not path.is_absolute() and base is not None:
        path = Path(base) / path
    if not path.exists():
        raise ValueError(f"file does not exist: {path}")
    return path.resolve()


ExistingPath = Annotated[Path, AfterValidator(_resolve_path)]
"""A path that must exist; relative paths resolve against the project file's folder."""

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
PositiveFloat = Annotated[float, Field(gt=0)]
NonNegativeFloat = Annotated[float, Field(ge=0)]


class PoseSpec(StrictModel):
    """A rigid pose: translation ``xyz`` in metres, rotation ``abc_deg`` = Rz(A) Ry(B) Rx(C)."""

    xyz: Vec3 = (0.0, 0.0, 0.0)
    abc_deg: Vec3 = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """The pose as a 4x4 homogeneous matrix (metres)."""
        T = np.eye(4)
        T[:3, :3] = matrix_from_abc(*np.radians(self.abc_deg))
        T[:3, 3] = self.xyz
        return T
