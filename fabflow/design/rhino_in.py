"""Elements from a Rhino .3dm file, read through rhino3dm (the optional ``interop`` extra).

What an object becomes:

* a box (a brep or extrusion with the eight corners of a box): a block; its
  frame chosen from the box's axes (:func:`fabflow.design.box_pose.box_pose_from_corners`);
* another brep or extrusion, or a mesh: a block, the smallest box around its
  vertices (:func:`fabflow.design.box_pose.oriented_box_pose`);
* a point with a ``fabflow.frame`` user text: a task point at that frame.

Its type comes from the user text ``fabflow.type``, else from its layer path
(a layer named ``block(s)`` or ``task_point(s)``, the innermost one counting),
else from the source's ``type``. Id, build-order layer, part, supports and frame
come from user text when present (keys in :mod:`fabflow.design.exchange`; a
frame there is in metres and is kept exactly), else the id from the object's
name or ``<file stem>-0000``, ... Objects on layers below
``fabflow::stations``, ``::anchors``, ``::setups`` and ``::as_built`` (what an
export adds beside the elements) are skipped, and so is every layer not named
in the source's ``layers`` when it names some.

Coordinates are scaled from the file's model units to metres.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fabflow.design import exchange
from fabflow.design.box_pose import box_pose_from_corners, oriented_box_pose
from fabflow.design.compas_in import MAX_MESH_VERTICES
from fabflow.design.element_records import ELEMENT_ID_PATTERN, ElementRecord, record
from fabflow.errors import InputError, UnsupportedError
from fabflow.files import input_file, strict_json
from fabflow.schema import MAX_MODEL_BYTES

UNIT_SCALE = {
    "Meters": 1.0,
    "Millimeters": 1e-3,
    "Centimeters": 1e-2,
    "Decimeters": 0.1,
    "Inches": 0.0254,
    "Feet": 0.3048,
}
"""Metres per model unit of the unit systems read."""
SKIPPED_LAYERS = tuple(
    exchange.LAYER_SEPARATOR.join((exchange.LAYER_ROOT, name))
    for name in (
        exchange.LAYER_STATIONS,
        exchange.LAYER_ANCHORS,
        exchange.LAYER_SETUPS,
        exchange.LAYER_AS_BUILT,
    )
)
_TYPE_LAYERS = {
    "block": "block",
    "blocks": "block",
    "task_point": "task_point",
    "task_points": "task_point",
}


def _rhino3dm() -> Any:
    try:
        import rhino3dm
    except ImportError:
        raise UnsupportedError(
            "reading .3dm files needs rhino3dm: pip install 'fabflow[interop]'"
        ) from None
    return rhino3dm


def _layer_paths(model: Any) -> list[str]:
    """Full ``parent::child`` path of every layer, by index."""
    layers = list(model.Layers)
    by_id = {str(layer.Id): layer for layer in layers}
    paths = []
    for layer in layers:
        names, seen, node = [], set(), layer
        while node is not None and str(node.Id) not in seen:
            seen.add(str(node.Id))
            names.append(node.Name or "")
            node = by_id.get(str(node.ParentLayerId))
        paths.append("::".join(reversed(names)))
    return paths


def _user_text(obj: Any) -> dict[str, str]:
    """fabflow's user text of an object: on its attributes, then on its geometry."""
    out: dict[str, str] = {}
    for holder in (obj.Geometry, obj.Attributes):
        for key, value in holder.GetUserStrings():
            if key.startswith(exchange.USER_TEXT_PREFIX):
                out[key] = value
    return out


def _points(geometry: Any, scale: float) -> np.ndarray:
    """Vertices of a brep, an extrusion or a mesh (metres)."""
    kind = type(geometry).__name__
    if kind == "Extrusion":
        geometry = geometry.ToBrep(True)
        kind = "Brep"
    if kind == "Brep":
        pts = [(v.Location.X, v.Location.Y, v.Location.Z) for v in geometry.Vertices]
    else:
        if len(geometry.Vertices) > MAX_MESH_VERTICES:
            raise ValueError(f"a mesh of more than {MAX_MESH_VERTICES} vertices")
        pts = [(p.X, p.Y, p.Z) for p in geometry.Vertices]
    return np.asarray(pts, dtype=float).reshape(-1, 3) * scale


def _frame(text: str) -> np.ndarray:
    values = strict_json(text)
    T = np.asarray(values, dtype=float)
    if T.shape != (16,) or not np.isfinite(T).all():
        raise ValueError(f"{exchange.KEY_FRAME} must hold 16 finite numbers")
    return T.reshape(4, 4)


def _type_of(text: dict[str, str], layer: str, default: str) -> str:
    if exchange.KEY_TYPE in text:
        return text[exchange.KEY_TYPE]
    for name in reversed(layer.split("::")):
        if name.lower() in _TYPE_LAYERS:
            return _TYPE_LAYERS[name.lower()]
    return default


def _object_data(obj: Any, layer: str, scale: float, default_type: str) -> dict[str, Any]:
    """Plain record data of one Rhino object."""
    text = _user_text(obj)
    geometry = obj.Geometry
    kind = type(geometry).__name__
    data: dict[str, Any] = {"type": _type_of(text, layer, default_type)}
    frame = _frame(text[exchange.KEY_FRAME]) if exchange.KEY_FRAME in text else None
    if kind == "Point":
        if frame is None:
            raise ValueError(f"a point needs a '{exchange.KEY_FRAME}' user text (its tool frame)")
        data["T_world_element"] = frame
        data["type"] = text.get(exchange.KEY_TYPE, "task_point")
    elif kind in ("Brep", "Extrusion", "Mesh"):
        points = _points(geometry, scale)
        if frame is not None:
            data["T_world_element"] = frame
            if exchange.KEY_EXTENTS in text:
                data["extents"] = strict_json(text[exchange.KEY_EXTENTS])
            else:
                local = (points - frame[:3, 3]) @ frame[:3, :3]
                data["extents"] = local.max(axis=0) - local.min(axis=0)
        elif kind != "Mesh" and len(points) == 8:
            T, ext = box_pose_from_corners(points[None])
            data["T_world_element"], data["extents"] = T[0], ext[0]
        else:
            data["T_world_element"], data["extents"] = oriented_box_pose(points)
    else:
        raise ValueError(f"a {kind} is not an element (use a box, a brep, a mesh or a point)")
    if exchange.KEY_ID in text:
        data["id"] = text[exchange.KEY_ID]
    elif obj.Attributes.Name and re.match(ELEMENT_ID_PATTERN, obj.Attributes.Name):
        data["id"] = obj.Attributes.Name
    if exchange.KEY_LAYER in text:
        data["layer"] = int(text[exchange.KEY_LAYER])
    if text.get(exchange.KEY_PART):
        data["part"] = text[exchange.KEY_PART]
    if exchange.KEY_SUPPORTS in text:
        data["supports"] = [s for s in text[exchange.KEY_SUPPORTS].split(",") if s]
    if exchange.KEY_ROBOT_BUILT in text:
        flag = text[exchange.KEY_ROBOT_BUILT].strip().lower()
        if flag not in ("true", "false"):
            raise ValueError(f"{exchange.KEY_ROBOT_BUILT} must be true or false")
        data["robot_built"] = flag == "true"
    data["T_world_element"] = np.asarray(data["T_world_element"]).tolist()
    if "extents" in data:
        data["extents"] = np.asarray(data["extents"]).tolist()
    return data


def read_3dm_elements(
    path: str | Path,
    max_elements: int,
    default_type: str = "block",
    layers: Sequence[str] = (),
    units: str = "auto",
) -> list[ElementRecord]:
    """The element records of a Rhino .3dm file.

    Parameters
    ----------
    path
        The file (at most :data:`fabflow.schema.MAX_MODEL_BYTES`).
    max_elements
        Most objects read (``limits.max_elements``).
    default_type
        Type of an object whose user text and layers do not say.
    layers
        Read only objects on these layers or below them (full paths,
        ``Walls::North``); empty: every layer but an export's extras.
    units
        ``"auto"`` (the file's model units) or a key of :data:`UNIT_SCALE`
        spelled ``m``, ``mm``, ``cm``, ``in``, ``ft``.

    Raises
    ------
    InputError
        For a file rhino3dm cannot read, unknown model units, too many objects,
        or an object that is not an element (named by its index, name and layer).
    UnsupportedError
        When rhino3dm is not installed.
    """
    rhino3dm = _rhino3dm()
    file = input_file(path, ".3dm file", MAX_MODEL_BYTES)
    model = rhino3dm.File3dm.Read(str(file))
    if model is None:
        raise InputError("not a Rhino .3dm file rhino3dm can read", path)
    if units == "auto":
        unit = model.Settings.ModelUnitSystem.name
        if unit not in UNIT_SCALE:
            raise InputError(
                f"the file's model units are {unit}; set 'units' (m, mm, cm, in or ft)", path
            )
        scale = UNIT_SCALE[unit]
    else:
        scale = {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "in": 0.0254, "ft": 0.3048}[units]
    paths = _layer_paths(model)
    wanted = tuple(layers)
    records: list[ElementRecord] = []
    stem = re.sub(r"[^A-Za-z0-9_.\-]", "_", Path(path).stem)[:50] or "element"
    for k, obj in enumerate(model.Objects):
        index = obj.Attributes.LayerIndex
        layer = paths[index] if 0 <= index < len(paths) else ""
        if any(layer == s or layer.startswith(s + "::") for s in SKIPPED_LAYERS):
            continue
        if wanted and not any(layer == s or layer.startswith(s + "::") for s in wanted):
            continue
        if len(records) >= max_elements:
            raise InputError(
                f"the file holds more than limits.max_elements ({max_elements}) objects", path
            )
        name = obj.Attributes.Name or ""
        where = f"object {k}" + (f" {name!r}" if name else "") + f" on layer {layer!r}"
        try:
            data = _object_data(obj, layer, scale, default_type)
        except ValueError as exc:
            raise InputError(f"{where}: {exc}", path) from None
        data.setdefault("id", f"{stem}-{k:04d}")
        records.append(record(data, path, where))
    return records
