"""The design and its plan as a Rhino .3dm file, written through rhino3dm (``interop`` extra).

Layers (all below :data:`~fabflow.design.exchange.LAYER_ROOT`, model units metres):

* ``fabflow::elements::<station>::<part>``: the elements each station builds,
  by part (``unplanned`` for elements no work package builds, ``no_part`` for
  elements without a part);
* ``fabflow::as_built``: the simulated as-built elements;
* ``fabflow::stations``: each station's platform outline at ground level (a
  closed polyline) and a text dot with its id at the platform origin;
* ``fabflow::anchors`` and ``fabflow::setups``: UWB anchors and total station
  set-ups as points named by their id.

A block or a stone slot is a box brep at the element's pose, a print path a
polyline in the world, a task point a point. Each element object is named by
its id and carries the user text of :func:`fabflow.design.export_data.element_user_text`
(its exact frame among it); each as-built object its id, type, station and
as-built frame.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from fabflow.design import exchange
from fabflow.design.elements import Element
from fabflow.design.export_data import (
    ExportContent,
    StationRecord,
    element_user_text,
    export_content,
    frame_text,
    world_polyline,
)
from fabflow.errors import InputError, UnsupportedError
from fabflow.output import atomic_file

FILE_VERSION = 7
"""The .3dm version written: Rhino 7 and 8 open it."""
MODEL_TOLERANCE = 1e-4
"""The model's absolute tolerance (metres)."""
STATION_COLOURS = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (23, 190, 207),
)
"""Layer colour of each station's elements, in order (RGB), repeated past the eighth."""
_GREY = (128, 128, 128)
_COLOURS = {
    exchange.LAYER_AS_BUILT: (230, 85, 13),
    exchange.LAYER_STATIONS: (0, 0, 0),
    exchange.LAYER_ANCHORS: (120, 40, 140),
    exchange.LAYER_SETUPS: (0, 110, 60),
}


def _rhino3dm() -> Any:
    try:
        import rhino3dm
    except ImportError:
        raise UnsupportedError(
            "writing .3dm files needs rhino3dm: pip install 'fabflow[interop]'"
        ) from None
    return rhino3dm


def layer_name(text: str) -> str:
    """A layer name for a station id or a part: ``::`` (Rhino's path separator) and
    control characters replaced by ``_``, blanks stripped."""
    name = "".join(c if c.isprintable() else "_" for c in text)
    return name.replace(exchange.LAYER_SEPARATOR, "_").strip() or "_"


class _Layers:
    """The layer tree of a model, made as paths are asked for."""

    def __init__(self, rhino3dm: Any, model: Any) -> None:
        self.r = rhino3dm
        self.model = model
        self.index: dict[tuple[str, ...], int] = {}

    def get(self, path: Iterable[str], colour: tuple[int, int, int] = _GREY) -> int:
        """Index of the layer at ``path`` (names from the root), made with ``colour`` if new."""
        path = tuple(path)
        if path in self.index:
            return self.index[path]
        layer = self.r.Layer()
        layer.Name = path[-1]
        layer.Color = (*colour, 255)
        if len(path) > 1:
            parent = self.get(path[:-1], colour)
            layer.ParentLayerId = self.model.Layers.FindIndex(parent).Id
        self.index[path] = self.model.Layers.Add(layer)
        return self.index[path]


def _xform(rhino3dm: Any, T: np.ndarray) -> Any:
    xf = rhino3dm.Transform(1.0)
    for i in range(4):
        for j in range(4):
            setattr(xf, f"M{i}{j}", float(T[i, j]))
    return xf


def _attributes(rhino3dm: Any, layer: int, name: str, text: Mapping[str, str]) -> Any:
    attributes = rhino3dm.ObjectAttributes()
    attributes.LayerIndex = layer
    attributes.Name = name
    for key, value in text.items():
        attributes.SetUserString(key, value)
    return attributes


def _add_element(rhino3dm: Any, model: Any, e: Element, T: np.ndarray, attributes: Any) -> None:
    """The element's geometry at pose ``T``: a box, a polyline or a point.

    A box is written as a capped extrusion (Rhino's light box: a twentieth of the
    size of a box brep in the file; Rhino shows and edits it as a solid).
    """
    if e.extents is not None:
        half = 0.5 * np.asarray(e.extents, dtype=float)
        box = rhino3dm.BoundingBox(rhino3dm.Point3d(*(-half)), rhino3dm.Point3d(*half))
        solid = rhino3dm.Extrusion.CreateBoxExtrusion(rhino3dm.Box(box), True)
        solid.Transform(_xform(rhino3dm, T))
        model.Objects.AddExtrusion(solid, attributes)
    elif e.polyline is not None and len(e.polyline) >= 2:
        points = [rhino3dm.Point3d(*p) for p in world_polyline(e, T).tolist()]
        model.Objects.AddCurve(rhino3dm.PolylineCurve(points), attributes)
    else:
        model.Objects.AddPoint(rhino3dm.Point3d(*T[:3, 3].tolist()), attributes)


def _station_colours(content: ExportContent) -> dict[str, tuple[int, int, int]]:
    return {s.id: STATION_COLOURS[k % len(STATION_COLOURS)] for k, s in enumerate(content.stations)}


def _add_elements(rhino3dm: Any, model: Any, layers: _Layers, content: ExportContent) -> None:
    colours = _station_colours(content)
    root = (exchange.LAYER_ROOT, exchange.LAYER_ELEMENTS)
    by_layer: dict[tuple[str, ...], list[Element]] = {}
    order = [*(s.id for s in content.stations), None]
    for e in content.elements:
        station = content.station_of.get(e.id)
        by_layer.setdefault((station or "", e.part or ""), []).append(e)
    # station layers in the plan's order, parts sorted, unplanned last
    keys = sorted(by_layer, key=lambda k: (order.index(k[0] or None), k[1]))
    for station, part in keys:
        path = (
            *root,
            layer_name(station) if station else exchange.LAYER_UNPLANNED,
            layer_name(part) if part else exchange.LAYER_NO_PART,
        )
        index = layers.get(path, colours.get(station, _GREY))
        for e in by_layer[(station, part)]:
            text = element_user_text(e, station or None)
            attributes = _attributes(rhino3dm, index, e.id, text)
            _add_element(rhino3dm, model, e, np.asarray(e.T_world_element, dtype=float), attributes)


def _add_as_built(rhino3dm: Any, model: Any, layers: _Layers, content: ExportContent) -> None:
    if not content.as_built:
        return
    index = layers.get(
        (exchange.LAYER_ROOT, exchange.LAYER_AS_BUILT), _COLOURS[exchange.LAYER_AS_BUILT]
    )
    for e in content.elements:
        T = content.as_built.get(e.id)
        if T is None:
            continue
        text = {
            exchange.KEY_ID: e.id,
            exchange.KEY_TYPE: e.type,
            exchange.KEY_FRAME: frame_text(T),
            exchange.KEY_STATION: content.station_of.get(e.id, ""),
        }
        attributes = _attributes(rhino3dm, index, e.id, {k: v for k, v in text.items() if v})
        _add_element(rhino3dm, model, e, T, attributes)


def _add_site(rhino3dm: Any, model: Any, layers: _Layers, content: ExportContent) -> None:
    if content.stations:
        path = (exchange.LAYER_ROOT, exchange.LAYER_STATIONS)
        index = layers.get(path, _COLOURS[exchange.LAYER_STATIONS])
        for s in content.stations:
            text = {
                exchange.KEY_STATION: s.id,
                exchange.KEY_FRAME: frame_text(s.T_world_platform),
            }
            corners = np.asarray(s.footprint, dtype=float).tolist()
            outline = [rhino3dm.Point3d(*p) for p in [*corners, corners[0]]]
            attributes = _attributes(rhino3dm, index, s.id, text)
            model.Objects.AddCurve(rhino3dm.PolylineCurve(outline), attributes)
            origin = rhino3dm.Point3d(*np.asarray(s.T_world_platform, dtype=float)[:3, 3].tolist())
            model.Objects.AddTextDot(s.id, origin, _attributes(rhino3dm, index, s.id, text))
    for name, points in (
        (exchange.LAYER_ANCHORS, content.anchors),
        (exchange.LAYER_SETUPS, content.setups),
    ):
        if not points:
            continue
        index = layers.get((exchange.LAYER_ROOT, name), _COLOURS[name])
        for pid, xyz in points.items():
            attributes = _attributes(rhino3dm, index, pid, {})
            model.Objects.AddPoint(rhino3dm.Point3d(*xyz.tolist()), attributes)


def rhino_model(
    elements: Sequence[Element],
    stations: Sequence[StationRecord] = (),
    anchors: Mapping[str, ArrayLike] | None = None,
    setups: Mapping[str, ArrayLike] | None = None,
    as_built: Mapping[str, ArrayLike] | None = None,
) -> Any:
    """The export as a ``rhino3dm.File3dm`` (see the module for its layers).

    Parameters
    ----------
    elements
        The elements (world frame, metres).
    stations
        The plan's stations (their elements go on their layers).
    anchors, setups
        UWB anchors and total station set-ups: name -> position (world, metres).
    as_built
        Simulated as-built pose (4x4, world, metres) by element id.

    Raises
    ------
    InputError
        As :func:`fabflow.design.export_data.export_content`.
    UnsupportedError
        When rhino3dm is not installed.
    """
    rhino3dm = _rhino3dm()
    content = export_content(elements, stations, anchors, setups, as_built)
    model = rhino3dm.File3dm()
    model.Settings.ModelUnitSystem = rhino3dm.UnitSystem.Meters
    model.Settings.ModelAbsoluteTolerance = MODEL_TOLERANCE
    layers = _Layers(rhino3dm, model)
    layers.get((exchange.LAYER_ROOT,))
    _add_elements(rhino3dm, model, layers, content)
    _add_as_built(rhino3dm, model, layers, content)
    _add_site(rhino3dm, model, layers, content)
    return model


def write_3dm(
    path: str | Path,
    elements: Sequence[Element],
    stations: Sequence[StationRecord] = (),
    anchors: Mapping[str, ArrayLike] | None = None,
    setups: Mapping[str, ArrayLike] | None = None,
    as_built: Mapping[str, ArrayLike] | None = None,
) -> Path:
    """Write the export as a Rhino .3dm file (:func:`rhino_model`), atomically.

    The file is written beside ``path`` and renamed into place: an existing file
    is replaced only by a complete one.

    Raises
    ------
    InputError
        As :func:`rhino_model`, or when the file cannot be written.
    UnsupportedError
        When rhino3dm is not installed.
    """
    model = rhino_model(elements, stations, anchors, setups, as_built)
    with atomic_file(path) as tmp:
        if not model.Write(str(tmp), FILE_VERSION):
            raise InputError("rhino3dm could not write the .3dm file", path)
    return Path(path)
