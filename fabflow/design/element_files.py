"""Read an ``elements: - file:`` source: pick the format, read, check, make elements."""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError

from fabflow.design.compas_in import read_compas_elements
from fabflow.design.element_records import (
    MAX_JSON_BYTES,
    ElementRecord,
    ElementsFile,
    record,
    records_to_elements,
    supports_given,
)
from fabflow.design.elements import Element
from fabflow.design.rhino_in import read_3dm_elements
from fabflow.design.specs import ElementFileSpec
from fabflow.errors import InputError
from fabflow.files import read_text, strict_json


def _json_format(doc: object) -> str:
    """``fabflow`` or ``compas``: which JSON an elements file holds."""
    items = doc.get("elements") if isinstance(doc, dict) else doc
    if isinstance(items, list) and items and isinstance(items[0], dict):
        if "T_world_element" in items[0]:
            return "fabflow"
        if "dtype" in items[0] or "geometry" in items[0]:
            return "compas"
    return "fabflow" if isinstance(doc, dict) and "frame" in doc else "compas"


def _fabflow_records(path: Path, doc: object, max_elements: int) -> list[ElementRecord]:
    """Records of an ``elements.json`` (the schema ``fabflow schema --elements`` prints)."""
    if not isinstance(doc, dict):
        raise InputError("an elements file is a JSON object with 'elements'", path)
    try:
        head = ElementsFile.model_validate(doc)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(p) for p in first["loc"])
        raise InputError(f"not an elements file: {loc}: {first['msg']}", path) from None
    if len(head.elements) > max_elements:
        raise InputError(
            f"the file holds {len(head.elements)} elements, more than limits.max_elements "
            f"({max_elements})",
            path,
        )
    if head.count is not None and head.count != len(head.elements):
        raise InputError(f"'count' is {head.count} but the file holds {len(head.elements)}", path)
    records = []
    for k, item in enumerate(head.elements):
        kind = item.get("type", "block")
        if kind not in ("block", "task_point"):
            raise InputError(
                f"elements[{k}]: a {kind} does not come from a file (print paths come from "
                "'print_path' sources, stones from a 'stone_wall')",
                path,
            )
        records.append(record(item, path, f"elements[{k}]"))
    return records


def file_elements(
    spec: ElementFileSpec, source_index: int, max_elements: int
) -> tuple[list[Element], bool]:
    """The elements of one file source, and whether their supports come from the file.

    Parameters
    ----------
    spec
        The source (its path already resolved against the project folder).
    source_index
        Index of the source in ``project.elements``.
    max_elements
        Most elements the file may hold (``limits.max_elements``).

    Returns
    -------
    tuple
        The elements, in file order; ``True`` when the blocks' supports are the
        file's, ``False`` when they are to be computed from the geometry.

    Raises
    ------
    InputError
        For a file that cannot be read or holds something that is not an element.
    """
    path = Path(spec.path)
    fmt = spec.format
    if fmt == "auto" and path.suffix.lower() == ".3dm":
        fmt = "3dm"
    if fmt == "3dm":
        records = read_3dm_elements(path, max_elements, spec.type, spec.layers, spec.units)
    elif fmt == "compas":
        records = read_compas_elements(path, max_elements)
    else:
        try:
            doc = strict_json(read_text(path, "elements file", MAX_JSON_BYTES))
        except ValueError as exc:
            raise InputError(f"not a JSON file: {exc}", path) from None
        if fmt == "auto":
            fmt = _json_format(doc)
        if fmt == "compas":
            records = read_compas_elements(path, max_elements)
        else:
            records = _fabflow_records(path, doc, max_elements)
    if spec.type != "block":
        records = [
            r if "type" in r.model_fields_set else r.model_copy(update={"type": spec.type})
            for r in records
        ]
    from_file = spec.supports == "file" or (spec.supports == "auto" and supports_given(records))
    elements = records_to_elements(
        records,
        path,
        source_index,
        max_elements,
        defaults={"part": spec.part, "robot_built": spec.robot_built},
    )
    return elements, from_file
