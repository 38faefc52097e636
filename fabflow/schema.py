"""Building blocks of the project schema, shared by every section.

:class:`StrictModel` is the base of every model of the project file (unknown
keys are errors, models are frozen); :class:`PoseSpec` is how a project file
writes a rigid pose; the annotated types carry the units and bounds the fields
share. The sections themselves live with the room that owns them
(:mod:`fabflow.design.specs` for what to build) and are put together in
:mod:`fabflow.project`.
"""

from __future__ import annotations

import difflib
import types
import typing
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, Strict, ValidationInfo

from fabflow.errors import InputError
from fabflow.files import MAX_TEXT_BYTES, input_file
from fabflow.transforms.so3 import matrix_from_abc

MAX_MAGNITUDE = 1e9
"""Largest magnitude of any number of a project, in the field's unit."""
MIN_POSITIVE = 1e-9
"""Smallest value of a field that must be positive (a length, a noise, a rate)."""
MAX_MODEL_BYTES = 2**30
"""Largest drawing, mesh or point-cloud map a project may name (bytes)."""


class StrictModel(BaseModel):
    """Base of every project model: unknown keys are errors, numbers are finite.

    Numbers are not coerced from text or booleans (see :data:`Real`,
    :data:`Count`, :data:`Switch`); NaN and infinity are refused everywhere,
    in tuples and mappings too.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


Real = Annotated[float, Strict(), Field(ge=-MAX_MAGNITUDE, le=MAX_MAGNITUDE)]
"""A finite number of magnitude at most :data:`MAX_MAGNITUDE`; an integer is fine,
text and booleans are not."""
PositiveFloat = Annotated[float, Strict(), Field(ge=MIN_POSITIVE, le=MAX_MAGNITUDE)]
"""A positive :data:`Real` (a length, a noise, a rate): at least :data:`MIN_POSITIVE`."""
NonNegativeFloat = Annotated[float, Strict(), Field(ge=0.0, le=MAX_MAGNITUDE)]
"""A :data:`Real` that is zero or positive (a standard deviation, a margin)."""
Fraction = Annotated[float, Strict(), Field(ge=0.0, le=1.0)]
"""A share or probability in [0, 1]."""
Count = Annotated[int, Strict(), Field(ge=0)]
"""A whole number written as one: ``3``, not ``3.0`` nor ``true``."""
PositiveCount = Annotated[int, Strict(), Field(ge=1)]
"""A :data:`Count` of at least 1."""
Switch = Annotated[bool, Strict()]
"""``true`` or ``false``, not ``1`` nor ``"yes"``."""
Vec2 = tuple[Real, Real]
Vec3 = tuple[Real, Real, Real]


def _project_file(value: Path, info: ValidationInfo, max_bytes: int) -> Path:
    """Resolve, contain and check a file named in a project (see :data:`ExistingPath`)."""
    context = info.context or {}
    path = Path(value).expanduser()
    if "base_dir" in context:  # read from a project file: stay inside its folder
        base = Path(context["base_dir"] or Path.cwd()).resolve()
        outside_ok = context.get("allow_outside_paths") is True
        if path.is_absolute() and not outside_ok:
            raise ValueError(
                "an absolute path; write it relative to the project folder "
                "(or set allow_outside_paths: true)"
            )
        path = (base / path).resolve()
        if not outside_ok and not path.is_relative_to(base):
            raise ValueError(
                "the path leads outside the project folder (set allow_outside_paths: true "
                "to allow it)"
            )
    try:
        return input_file(path, "file", max_bytes).resolve()
    except InputError as exc:
        raise ValueError(f"{exc.message}: {path}") from None


def _text_file(value: Path, info: ValidationInfo) -> Path:
    return _project_file(value, info, MAX_TEXT_BYTES)


def _model_file(value: Path, info: ValidationInfo) -> Path:
    return _project_file(value, info, MAX_MODEL_BYTES)


ExistingPath = Annotated[Path, AfterValidator(_text_file)]
"""A regular file of at most :data:`fabflow.files.MAX_TEXT_BYTES`. In a project file
(validated with a ``base_dir`` in the context) it lies inside the project folder:
relative paths resolve against it; absolute paths and paths leading out of it
(``../``, a symbolic link) only with ``allow_outside_paths: true``. Built in
Python, a relative path resolves against the working folder."""
ModelPath = Annotated[Path, AfterValidator(_model_file)]
"""As :data:`ExistingPath`, for a drawing, mesh or map of at most :data:`MAX_MODEL_BYTES`."""


def _field_names(annotation: Any) -> list[str]:
    """Field names of the models an annotation holds (through lists, unions, mappings)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return list(annotation.model_fields)
    names: list[str] = []
    for arg in typing.get_args(annotation):
        names += _field_names(arg)
    return names


def _field_type(annotation: Any, part: Any) -> Any:
    """The annotation one step down ``part`` (a field name or an index) from ``annotation``."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        field = annotation.model_fields.get(part) if isinstance(part, str) else None
        return None if field is None else field.annotation
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (list, tuple) and isinstance(part, int) and args:
        return args[0]
    if origin is dict and len(args) == 2:
        return args[1]
    if origin in (typing.Union, types.UnionType, Annotated):
        found = [t for a in args if (t := _field_type(a, part)) is not None]
        return typing.Union[tuple(found)] if len(found) > 1 else (found[0] if found else None)  # noqa: UP007
    return None


def near_field(model: type[BaseModel], loc: tuple[Any, ...]) -> str | None:
    """The known field nearest to an unknown key: ``loc`` is the key's path in ``model``.

    Returns
    -------
    str or None
        A field name of the model that holds the key, when one is close enough
        (:func:`difflib.get_close_matches`).
    """
    annotation: Any = model
    for part in loc[:-1]:
        annotation = _field_type(annotation, part)
        if annotation is None:
            return None
    key = loc[-1] if loc else None
    if not isinstance(key, str):
        return None
    close = difflib.get_close_matches(key, _field_names(annotation), n=1, cutoff=0.6)
    return close[0] if close else None


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


class Limits(StrictModel):
    """The most work a project may ask for; a larger job raises them in ``limits:``.

    Checked when the project is validated (from what the file says) and when a
    drawing or mesh is read (from what it holds), before the work is done. The
    defaults are far above the example projects and far below what fills a
    24 GiB machine.
    """

    max_elements: PositiveCount = 100_000
    """Elements: cabin blocks (an upper bound from the walls, openings and layers),
    print path layers (mesh slices), task points."""
    max_path_samples: PositiveCount = 20_000_000
    """Samples of all print paths at their ``sample_rate_hz`` and ``speed``."""
    max_candidates: PositiveCount = 4_000_000
    """Candidate platform poses of the station planner: grid points of the site at
    ``planning.candidate_spacing`` times ``planning.headings_deg``."""
    max_sensor_samples: PositiveCount = 1_000_000
    """Simulated measurements per station: UWB ranges (``dwell_s * rate_hz`` per tag
    and anchor) and IMU records (``dwell_s * imu_rate_hz``)."""
    max_runs: PositiveCount = 100_000
    """``simulation.runs``."""
