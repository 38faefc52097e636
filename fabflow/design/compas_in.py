"""Elements from a COMPAS JSON file (COMPAS 2 data, written by ``compas.json_dump``).

The file holds a list, or an object whose ``elements`` is a list (the form
``fabflow export`` writes). Each item is a COMPAS object or a record:

* ``compas.geometry/Box``: a block; its centre and size from the box, its frame
  chosen from the box's axes as for any drawn box
  (:func:`fabflow.design.box_pose.canonical_frames`);
* ``compas.datastructures/Mesh``: a block, the smallest box around the mesh;
* ``compas.geometry/Frame``: a task point, the frame the tool reaches;
* a record: an object with ``geometry`` (one of the above) and any of ``id``,
  ``type``, ``frame`` (a Frame: the element frame, kept exactly), ``layer``,
  ``part``, ``supports``, ``robot_built``, ``attributes``.

The COMPAS objects are decoded by compas (the optional ``interop`` extra),
after the file's ``dtype`` names are checked against the ones above: decoding
imports the class a ``dtype`` names, which a file must not choose freely.
Objects without an id are named ``<file stem>-0000``, ``-0001``, ...
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from fabflow.design.box_pose import canonical_frames, oriented_box_pose
from fabflow.design.element_records import (
    ELEMENT_ID_PATTERN,
    MAX_JSON_BYTES,
    ElementRecord,
    record,
)
from fabflow.errors import InputError, UnsupportedError
from fabflow.files import read_text, strict_json

ALLOWED_DTYPES = frozenset(
    {
        "compas.geometry/Box",
        "compas.geometry/Frame",
        "compas.geometry/Point",
        "compas.geometry/Vector",
        "compas.geometry/Polyline",
        "compas.datastructures/Mesh",
    }
)
"""COMPAS types a file may hold (points, vectors and polylines only inside an
export's other records, which are not elements)."""
MAX_MESH_VERTICES = 2_000_000
"""Most mesh vertices one file may hold."""
_RECORD_KEYS = frozenset(
    {"id", "type", "frame", "geometry", "layer", "part", "supports", "robot_built", "attributes"}
)
_EXPORT_ONLY = frozenset({"station"})


def _dtypes(node: Any) -> Iterator[str]:
    """Every ``dtype`` named anywhere in a parsed JSON document."""
    stack = [node]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            if isinstance(item.get("dtype"), str):
                yield item["dtype"]
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)


def _compas() -> Any:
    try:
        import compas
    except ImportError:
        raise UnsupportedError(
            "reading COMPAS JSON needs compas: pip install 'fabflow[interop]'"
        ) from None
    return compas


def frame_matrix(frame: Any) -> np.ndarray:
    """4x4 pose of a COMPAS Frame (columns x, y, z axes, then its point), metres."""
    T = np.eye(4)
    T[:3, 0] = np.asarray(frame.xaxis, dtype=float)
    T[:3, 1] = np.asarray(frame.yaxis, dtype=float)
    T[:3, 2] = np.asarray(frame.zaxis, dtype=float)
    T[:3, 3] = np.asarray(frame.point, dtype=float)
    return T


def _geometry_record(geometry: Any, where: str) -> dict[str, Any]:
    """``type``, ``T_world_element`` and ``extents`` of one COMPAS object."""
    kind = type(geometry).__name__
    if kind == "Box":
        T = frame_matrix(geometry.frame)
        R, ext = canonical_frames(
            T[None, :3, :3], np.array([[geometry.xsize, geometry.ysize, geometry.zsize]])
        )
        T[:3, :3] = R[0]
        return {"type": "block", "T_world_element": T, "extents": ext[0]}
    if kind == "Frame":
        return {"type": "task_point", "T_world_element": frame_matrix(geometry)}
    if kind == "Mesh":
        points = np.asarray([geometry.vertex_coordinates(v) for v in geometry.vertices()])
        try:
            T, ext = oriented_box_pose(points)
        except ValueError as exc:
            raise ValueError(f"{where}: the mesh: {exc}") from None
        return {"type": "block", "T_world_element": T, "extents": ext}
    raise ValueError(f"{where}: a {kind} is not an element (use a Box, a Mesh or a Frame)")


def _extents_in(T: np.ndarray, geometry: Any) -> np.ndarray:
    """Size of a box or mesh along the axes of the element frame ``T``."""
    if type(geometry).__name__ == "Box":
        corners = np.asarray(geometry.points, dtype=float)
    else:
        corners = np.asarray([geometry.vertex_coordinates(v) for v in geometry.vertices()])
    local = (corners - T[:3, 3]) @ T[:3, :3]
    return local.max(axis=0) - local.min(axis=0)


def _item(item: Any, k: int, stem: str) -> dict[str, Any]:
    """Plain record data of one list item (a COMPAS object or a record)."""
    where = f"elements[{k}]"
    if isinstance(item, dict):
        unknown = set(item) - _RECORD_KEYS - _EXPORT_ONLY
        if unknown:
            raise ValueError(f"{where}: unknown key {sorted(unknown)[0]!r}")
        if "geometry" not in item:
            raise ValueError(f"{where}: a record needs its 'geometry'")
        data = _geometry_record(item["geometry"], where)
        if item.get("frame") is not None:
            if type(item["frame"]).__name__ != "Frame":
                raise ValueError(f"{where}: 'frame' must be a COMPAS Frame")
            data["T_world_element"] = frame_matrix(item["frame"])
            if "extents" in data:
                data["extents"] = _extents_in(data["T_world_element"], item["geometry"])
        data.update({k2: v for k2, v in item.items() if k2 in _RECORD_KEYS - {"frame", "geometry"}})
    else:
        data = _geometry_record(item, where)
        name = getattr(item, "name", None)
        if isinstance(name, str) and name != type(item).__name__:
            data["id"] = name
    data.setdefault("id", f"{stem}-{k:04d}")
    data["T_world_element"] = np.asarray(data["T_world_element"]).tolist()
    if data.get("extents") is not None:
        data["extents"] = np.asarray(data["extents"]).tolist()
    return data


def read_compas_elements(path: str | Path, max_elements: int) -> list[ElementRecord]:
    """The element records of a COMPAS JSON file.

    Parameters
    ----------
    path
        The file (UTF-8 JSON, at most :data:`fabflow.schema.MAX_MODEL_BYTES`).
    max_elements
        Most items the file may hold (``limits.max_elements``).

    Raises
    ------
    InputError
        For a file that is not JSON, names a type outside :data:`ALLOWED_DTYPES`,
        holds too many items or mesh vertices, or an item that is not an element.
    UnsupportedError
        When compas is not installed.
    """
    text = read_text(path, "COMPAS JSON file", MAX_JSON_BYTES)
    try:
        doc = strict_json(text)
    except ValueError as exc:
        raise InputError(f"not a JSON file: {exc}", path) from None
    items = doc.get("elements") if isinstance(doc, dict) else doc
    if not isinstance(items, list):
        raise InputError("expected a list of COMPAS objects, or an object with 'elements'", path)
    if len(items) > max_elements:
        raise InputError(
            f"the file holds {len(items)} items, more than limits.max_elements ({max_elements})",
            path,
        )
    bad = next((d for d in _dtypes(doc) if d not in ALLOWED_DTYPES), None)
    if bad is not None:
        raise InputError(
            f"COMPAS type {bad!r} is not read here (known: {', '.join(sorted(ALLOWED_DTYPES))})",
            path,
        )
    vertices = text.count('"x"')  # each mesh vertex has one x coordinate
    if vertices > MAX_MESH_VERTICES:
        raise InputError(f"the meshes hold more than {MAX_MESH_VERTICES} vertices", path)
    compas = _compas()
    try:
        decoded = compas.json_loads(text)
    except Exception as exc:  # compas raises what its decoders raise
        raise InputError(f"not COMPAS data: {type(exc).__name__}: {exc}", path) from None
    objects = decoded["elements"] if isinstance(decoded, dict) else decoded
    stem = re.sub(r"[^A-Za-z0-9_.\-]", "_", Path(path).stem)[:50] or "element"
    records = []
    for k, item in enumerate(objects):
        try:
            data = _item(item, k, stem)
        except (ValueError, TypeError, AttributeError) as exc:
            raise InputError(str(exc), path) from None
        if not re.match(ELEMENT_ID_PATTERN, str(data["id"])):
            raise InputError(f"elements[{k}]: id {str(data['id'])[:70]!r} is not an id", path)
        records.append(record(data, path, f"elements[{k}]"))
    return records
