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
import functools
import re
import types
import typing
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    ValidationError,
    ValidationInfo,
)
from pydantic_core import PydanticCustomError

from fabflow.errors import InputError
from fabflow.files import MAX_TEXT_BYTES, input_file
from fabflow.transforms.so3 import matrix_from_abc
from fabflow.yaml_input import line_of

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


def located(loc: tuple[Any, ...], message: str) -> PydanticCustomError:
    """A validation error of the field at ``loc`` (raised by a model above it)."""
    return PydanticCustomError("located", "{message}", {"message": message, "at": loc})


def format_loc(loc: tuple[Any, ...]) -> str:
    """Turn a pydantic error location into a field path such as ``elements[2].cabin.x``."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif not out:
            out = str(part)
        else:
            out += f".{part}"
    return out or "(top level)"


_UNION_BRANCH = re.compile(r"(constrained-)?(float|str|int|bool)$")


def _field_loc(error: Any) -> tuple[Any, ...]:
    """The field path of a pydantic error, without the branch name a union adds at its end."""
    if error["type"] == "located":
        return tuple(error["ctx"]["at"])
    loc = tuple(error["loc"])
    branch = loc and isinstance(loc[-1], str) and _UNION_BRANCH.match(loc[-1])
    if branch and error["type"] not in ("missing", "extra_forbidden"):
        loc = loc[:-1]
    return loc


def _describe(error: Any, model: type[BaseModel], loc: tuple[Any, ...]) -> str:
    kind = error["type"]
    if kind == "missing":
        return "required field is missing"
    if kind == "extra_forbidden":
        near = near_field(model, loc)
        hint = f"; did you mean '{near}'?" if near else ""
        return f"unknown key (not part of the project schema){hint}"
    msg = error["msg"]
    for prefix in ("Value error, ", "Assertion failed, "):
        msg = msg.removeprefix(prefix)
    given = error.get("input")
    if kind != "located" and given is not None and not isinstance(given, dict | list):
        shown = repr(given)
        if len(shown) <= 60:
            msg += f" (got {shown})"
    return msg


def error_lines(exc: ValidationError, model: type[BaseModel], node: yaml.Node | None) -> list[str]:
    """One line per problem: ``line N: field.path: what is wrong`` (did you mean, got ...).

    Parameters
    ----------
    exc
        The validation error of ``model``.
    model
        The model validated (for the field names an unknown key is near).
    node
        The YAML node tree of the document (for the lines).
    """
    lines = []
    seen = set()
    for error in exc.errors():
        loc = _field_loc(error)
        if loc in seen:  # the other branch of a union (a number or a text)
            continue
        seen.add(loc)
        line = line_of(node, loc)
        at = f"line {line}: " if line else ""
        lines.append(f"{at}{format_loc(loc)}: {_describe(error, model, loc)}")
    return lines


class PoseSpec(StrictModel):
    """A rigid pose: translation ``xyz`` in metres, rotation ``abc_deg`` = Rz(A) Ry(B) Rx(C)."""

    xyz: Vec3 = (0.0, 0.0, 0.0)
    abc_deg: Vec3 = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """The pose as a 4x4 homogeneous matrix (metres); a fresh array each call."""
        values = np.array([*self.xyz, *self.abc_deg], dtype=float)
        return _pose_matrix(values.tobytes()).copy()


@functools.lru_cache(maxsize=1024)
def _pose_matrix(values: bytes) -> np.ndarray:
    """:meth:`PoseSpec.matrix` of ``xyz`` and ``abc_deg`` (their six float64 bytes, so
    that -0.0 and 0.0 stay apart), made once: a simulated run asks for a project's few
    poses at every visit."""
    xyz, abc_deg = np.frombuffer(values, dtype=float).reshape(2, 3)
    T = np.eye(4)
    T[:3, :3] = matrix_from_abc(*np.radians(abc_deg))
    T[:3, 3] = xyz
    T.flags.writeable = False
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
