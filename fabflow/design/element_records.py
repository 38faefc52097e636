"""Elements given in a file: the record every reader produces, and elements.json's schema.

An elements file (``elements: - file: walls.json``) holds elements the user
made elsewhere: in Grasshopper, COMPAS or their own scripts. Each reader
(fabflow's own ``elements.json``, COMPAS JSON, Rhino .3dm) turns what it reads
into :class:`ElementRecord` objects; :func:`records_to_elements` checks them as
one set and makes the elements. :func:`elements_file_schema` is the JSON Schema
of ``elements.json``, the file ``fabflow build`` writes and reads back.

Only blocks and task points come from files: a print path needs the bead and
speed the ``print_path`` source computes, a stone the scans of ``stone_wall``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator

from fabflow.design.elements import Element
from fabflow.design.specs import MAX_LAYER
from fabflow.errors import InputError
from fabflow.schema import MAX_MAGNITUDE, Count, PositiveFloat, Real, StrictModel, Switch
from fabflow.transforms.errors import RotationError
from fabflow.transforms.so3 import check_rotation

ELEMENT_ID_PATTERN = r"^[A-Za-z0-9_.:\-]{1,64}$"
"""Ids of file elements: letters, digits and ``_ . : -``, at most 64 (they appear in
program comments and file names)."""
FILE_ELEMENT_TYPES = ("block", "task_point")
"""The element types a file may hold."""
MAX_JSON_BYTES = 256 * 2**20
"""Largest JSON elements file (bytes): some 300,000 indented elements."""
FRAME_TOLERANCE = 1e-6
"""Largest entry of ``|R^T R - I|`` accepted in a file's element frame."""

ElementId = Annotated[str, Field(pattern=ELEMENT_ID_PATTERN)]
Size = tuple[PositiveFloat, PositiveFloat, PositiveFloat]


class ElementRecord(StrictModel):
    """One element as a file gives it (metres, world frame).

    ``T_world_element`` is the element frame: for a block its centre, x along
    its length, z up; for a task point the tool frame to reach. ``supports``
    ``None`` means the file does not say (they are computed from the geometry).
    """

    id: ElementId
    type: Literal[FILE_ELEMENT_TYPES] = "block"  # type: ignore[valid-type]
    T_world_element: tuple[
        tuple[Real, Real, Real, Real],
        tuple[Real, Real, Real, Real],
        tuple[Real, Real, Real, Real],
        tuple[Real, Real, Real, Real],
    ]
    layer: Annotated[Count, Field(le=MAX_LAYER)] | None = None
    """Build-order layer (0 = lowest); ``None``: blocks by the height of their
    bottom face (1 mm bins), task points 0."""
    supports: list[ElementId] | None = None
    part: Annotated[str, Field(min_length=1, max_length=64)] | None = None
    robot_built: Switch = True
    extents: Size | None = None
    """Block size (length along x, width along y, height along z), metres."""
    attributes: Annotated[
        dict[str, Real | str | bool | dict[str, Real | str]], Field(max_length=64)
    ] = {}
    """Extra plain data; for a task point ``action`` (drill, mark or measure)."""

    @field_validator("T_world_element")
    @classmethod
    def _rigid(cls, T: tuple[tuple[float, ...], ...]) -> tuple[tuple[float, ...], ...]:
        M = np.asarray(T, dtype=float)
        if not np.array_equal(M[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError("the last row of a pose must be [0, 0, 0, 1]")
        try:
            check_rotation(M[:3, :3], FRAME_TOLERANCE, "the pose's rotation")
        except RotationError as exc:
            raise ValueError(str(exc)) from None
        return T


class ElementsFile(StrictModel):
    """The schema of ``elements.json``: elements in the world frame, metres."""

    frame: Literal["world"] = "world"
    units: Literal["m"] = "m"
    count: Count | None = None
    """Number of elements (checked when given)."""
    elements: list[dict[str, Any]]
    """One object per element; blocks and task points as :class:`ElementRecord`,
    other types as ``fabflow build`` writes them."""


def elements_file_schema() -> dict[str, Any]:
    """JSON Schema of an ``elements.json`` a project may name (``elements: - file:``).

    ``fabflow schema --elements`` prints it.
    """
    schema = ElementsFile.model_json_schema()
    schema["properties"]["elements"]["items"] = ElementRecord.model_json_schema()
    schema["title"] = "fabflow elements file"
    schema["properties"]["elements"]["items"].pop("title", None)
    return schema


def record(data: dict[str, Any], source: str | Path, where: str) -> ElementRecord:
    """One :class:`ElementRecord` from plain data, or an :class:`InputError` naming ``where``."""
    try:
        return ElementRecord.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(p) for p in first["loc"])
        what = first["msg"].removeprefix("Value error, ")
        raise InputError(f"{where}: {loc}: {what}" if loc else f"{where}: {what}", source) from None


def records_to_elements(
    records: Sequence[ElementRecord],
    source: str | Path,
    source_index: int,
    max_elements: int,
    defaults: dict[str, Any] | None = None,
) -> list[Element]:
    """Elements of one file, checked as a set.

    Parameters
    ----------
    records
        What the file holds, in file order.
    source
        The file, named in error messages.
    source_index
        Index of the source in ``project.elements`` (kept in the attributes).
    max_elements
        Most elements the file may hold (``limits.max_elements``).
    defaults
        ``part`` and ``robot_built`` for records that do not give them.

    Raises
    ------
    InputError
        For an empty file, more than ``max_elements``, an id used twice, a block
        without ``extents``, a support naming an element not in the file, a
        task point with an unknown action, or a coordinate beyond the bounds.
    """
    if not records:
        raise InputError("the file holds no elements", source)
    if len(records) > max_elements:
        raise InputError(
            f"the file holds {len(records)} elements, more than limits.max_elements "
            f"({max_elements})",
            source,
        )
    counts = Counter(r.id for r in records)
    dup = next((k for k, v in counts.items() if v > 1), None)
    if dup is not None:
        raise InputError(f"element id {dup!r} is used twice", source)
    defaults = defaults or {}
    layers = _layers(records)
    out = []
    for r, layer in zip(records, layers, strict=True):
        if r.type == "block" and r.extents is None:
            raise InputError(f"element {r.id}: a block needs 'extents'", source)
        if r.type == "task_point" and r.attributes.get("action", "mark") not in (
            "drill",
            "mark",
            "measure",
        ):
            raise InputError(
                f"element {r.id}: a task point's action is drill, mark or measure "
                f"(got {r.attributes['action']!r})",
                source,
            )
        missing = [s for s in r.supports or () if s not in counts]
        if missing:
            raise InputError(
                f"element {r.id}: rests on {missing[0]!r}, which is not in the file", source
            )
        attributes: dict[str, Any] = {**r.attributes, "source_index": source_index}
        if r.type == "task_point":
            attributes.setdefault("action", "mark")
            attributes.setdefault("params", {})
        out.append(
            Element(
                id=r.id,
                type=r.type,
                T_world_element=np.asarray(r.T_world_element, dtype=float),
                layer=layer,
                supports=tuple(r.supports or ()),
                part=r.part if r.part is not None else defaults.get("part"),
                robot_built=r.robot_built
                if "robot_built" in r.model_fields_set
                else defaults.get("robot_built", True),
                extents=None if r.extents is None else np.asarray(r.extents, dtype=float),
                attributes=attributes,
            )
        )
    reach = max(float(np.abs(e.T_world_element[:3, 3]).max()) for e in out)
    if reach > MAX_MAGNITUDE:
        raise InputError(f"an element lies {reach:.3g} m from the origin", source)
    return out


def _layers(records: Sequence[ElementRecord]) -> list[int]:
    """Each record's layer: as given, else a block's rank among the bottom heights."""
    T = np.array([r.T_world_element for r in records], dtype=float)
    ext = np.array([r.extents if r.extents is not None else (0.0, 0.0, 0.0) for r in records])
    # the lowest point of the box: centre z minus the half extents along each axis' z
    bottom = T[:, 2, 3] - 0.5 * np.einsum("mk,mk->m", np.abs(T[:, 2, :3]), ext)
    level = np.round(bottom / 1e-3).astype(np.int64)
    free = np.array([r.layer is None and r.type == "block" for r in records])
    rank = np.zeros(len(records), dtype=np.int64)
    if free.any():
        _, inverse = np.unique(level[free], return_inverse=True)
        rank[free] = inverse
    return [r.layer if r.layer is not None else int(k) for r, k in zip(records, rank, strict=True)]


def supports_given(records: Sequence[ElementRecord]) -> bool:
    """Whether the file says what rests on what (any record names its supports)."""
    return any(r.supports is not None for r in records)
