"""The design and its plan as a COMPAS JSON file (``compas.json_load`` reads it; ``interop`` extra).

The document (world frame, metres)::

    {"fabflow": 1, "units": "m", "frame": "world",
     "elements": [{"id", "type", "layer", "part", "supports", "robot_built",
                   "station", "attributes", "frame": Frame,
                   "geometry": Box | Polyline | Frame}, ...],
     "stations": [{"id", "frame": Frame, "footprint": Polyline, "elements": [ids]}, ...],
     "anchors": [{"name", "point": Point}, ...],
     "setups": [{"name", "point": Point}, ...],
     "as_built": [{"id", "frame": Frame}, ...]}

``"fabflow"`` is the format version
(:data:`~fabflow.design.exchange.COMPAS_FORMAT_VERSION`). An element's frame is
``T_world_element``; its geometry a ``Box(xsize, ysize, zsize, frame)`` centred
on it for a block or a stone slot, a ``Polyline`` in the world for a print path,
its ``Frame`` for a task point. ``station`` is ``None`` for an element no work
package builds, ``part`` for one without a part. A station's frame is its
platform pose, its footprint the platform's outline at ground level, closed.

Frames are made from the pose's origin and x and y axes, so
``Transformation.from_frame(frame)`` gives the pose back to rounding (1e-15).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from fabflow.design import exchange
from fabflow.design.elements import Element
from fabflow.design.export_data import StationRecord, export_content, world_polyline
from fabflow.errors import InputError, UnsupportedError
from fabflow.json_format import json_safe
from fabflow.output import atomic_file


def _compas() -> Any:
    try:
        import compas
        import compas.geometry
    except ImportError:
        raise UnsupportedError(
            "writing COMPAS JSON needs compas: pip install 'fabflow[interop]'"
        ) from None
    return compas


def compas_frame(T: ArrayLike) -> Any:
    """A ``compas.geometry.Frame`` of a pose (4x4, metres): its origin, x and y axes."""
    geometry = _compas().geometry
    T = np.asarray(T, dtype=float)
    return geometry.Frame(T[:3, 3].tolist(), T[:3, 0].tolist(), T[:3, 1].tolist())


def _geometry(geometry: Any, e: Element, frame: Any) -> Any:
    if e.extents is not None:
        x, y, z = np.asarray(e.extents, dtype=float).tolist()
        return geometry.Box(x, y, z, frame=frame)
    if e.polyline is not None:
        return geometry.Polyline(world_polyline(e).tolist())
    return frame


def compas_document(
    elements: Sequence[Element],
    stations: Sequence[StationRecord] = (),
    anchors: Mapping[str, ArrayLike] | None = None,
    setups: Mapping[str, ArrayLike] | None = None,
    as_built: Mapping[str, ArrayLike] | None = None,
) -> dict[str, Any]:
    """The export as a document of COMPAS objects (see the module).

    Parameters
    ----------
    elements
        The elements (world frame, metres).
    stations
        The plan's stations.
    anchors, setups
        UWB anchors and total station set-ups: name -> position (world, metres).
    as_built
        Simulated as-built pose (4x4, world, metres) by element id.

    Raises
    ------
    InputError
        As :func:`fabflow.design.export_data.export_content`.
    UnsupportedError
        When compas is not installed.
    """
    geometry = _compas().geometry
    content = export_content(elements, stations, anchors, setups, as_built)
    records = []
    for e in content.elements:
        frame = compas_frame(e.T_world_element)
        records.append(
            {
                "id": e.id,
                "type": e.type,
                "layer": int(e.layer),
                "part": e.part,
                "supports": list(e.supports),
                "robot_built": bool(e.robot_built),
                "station": content.station_of.get(e.id),
                "attributes": json_safe(e.attributes),
                "frame": frame,
                "geometry": _geometry(geometry, e, frame),
            }
        )
    station_records = []
    for s in content.stations:
        corners = np.asarray(s.footprint, dtype=float).tolist()
        station_records.append(
            {
                "id": s.id,
                "frame": compas_frame(s.T_world_platform),
                "footprint": geometry.Polyline([*corners, corners[0]]),
                "elements": list(s.elements),
            }
        )
    return {
        exchange.COMPAS_FORMAT_KEY: exchange.COMPAS_FORMAT_VERSION,
        "units": "m",
        "frame": "world",
        "elements": records,
        "stations": station_records,
        "anchors": [
            {"name": k, "point": geometry.Point(*p.tolist())} for k, p in content.anchors.items()
        ],
        "setups": [
            {"name": k, "point": geometry.Point(*p.tolist())} for k, p in content.setups.items()
        ],
        "as_built": [
            {"id": e.id, "frame": compas_frame(content.as_built[e.id])}
            for e in content.elements
            if e.id in content.as_built
        ],
    }


def write_compas_json(
    path: str | Path,
    elements: Sequence[Element],
    stations: Sequence[StationRecord] = (),
    anchors: Mapping[str, ArrayLike] | None = None,
    setups: Mapping[str, ArrayLike] | None = None,
    as_built: Mapping[str, ArrayLike] | None = None,
) -> Path:
    """Write the export as COMPAS JSON (:func:`compas_document`), atomically.

    Written with ``compas.json_dump`` without GUIDs, so the same export gives
    the same file; beside ``path`` first and renamed into place.

    Raises
    ------
    InputError
        As :func:`compas_document`, or when the file cannot be written.
    UnsupportedError
        When compas is not installed.
    """
    compas = _compas()
    document = compas_document(elements, stations, anchors, setups, as_built)
    with atomic_file(path) as tmp:
        try:
            compas.json_dump(document, str(tmp), minimal=True)
        except OSError as exc:
            raise InputError(f"cannot write the file: {exc.strerror or exc}", path) from None
    return Path(path)
