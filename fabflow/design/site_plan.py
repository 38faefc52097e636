"""Write a site plan DXF: element footprints, print paths, task points, stations, sensors.

The plan is the world xy plane seen from above, in millimetres (``$INSUNITS`` =
4), one named layer per kind of thing so a CAD user can switch them on and off:

========================  ==============================================================
layer                     content
========================  ==============================================================
``FOOTPRINT``             outline of all blocks together
``PART_<name>``           outline of the blocks of one part, labelled with the part name
``PRINT_PATH``            the first printed layer of every print path (extruding runs)
``TASK_POINTS``           a point, a circle and the id of every task point
``STATIONS``              every station's origin, heading and id
``PLATFORMS``             the platform footprint at every station
``UWB_ANCHORS``           UWB anchors (circle, name and height)
``TOTAL_STATION``         total-station setups (triangle and name)
========================  ==============================================================
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import ezdxf
import numpy as np
import shapely
from numpy.typing import ArrayLike

from fabflow.design.elements import Element
from fabflow.design.supports import box_corners, box_footprints

MM = 1000.0
TEXT_HEIGHT = 100.0
"""Label height (millimetres)."""

_LAYERS = {
    "FOOTPRINT": 7,
    "PRINT_PATH": 1,
    "TASK_POINTS": 3,
    "STATIONS": 5,
    "PLATFORMS": 4,
    "UWB_ANCHORS": 6,
    "TOTAL_STATION": 2,
    "CONTROL_POINTS": 1,
}
_PART_COLOURS = (30, 140, 200, 40, 90, 170, 230)


def _station_fields(station: Any) -> tuple[str, np.ndarray]:
    if isinstance(station, Mapping):
        return str(station["id"]), np.asarray(station["T_world_platform"], dtype=float)
    return str(station.id), np.asarray(station.T_world_platform, dtype=float)


def _instrument_setups(instrument: Any) -> list[tuple[str, np.ndarray]]:
    """Normalise the ``instrument`` argument to (name, xyz in metres) pairs."""
    if instrument is None:
        return []
    if isinstance(instrument, Mapping):
        items = list(instrument.items())
    else:
        a = np.asarray(instrument, dtype=float)
        if a.shape in ((3,), (4, 4)):
            items = [("TS", a)]
        else:
            items = [(f"TS{i + 1}", x) for i, x in enumerate(a)]
    out = []
    for name, x in items:
        a = np.asarray(x, dtype=float)
        out.append((str(name), a[:3, 3] if a.shape == (4, 4) else a.reshape(3)))
    return out


def _add_polygon(msp: Any, geom: Any, layer: str) -> None:
    polys = getattr(geom, "geoms", [geom])
    for poly in polys:
        if poly.is_empty or poly.geom_type != "Polygon":
            continue
        for ring in [poly.exterior, *poly.interiors]:
            pts = np.asarray(ring.coords)[:-1] * MM
            msp.add_lwpolyline(pts.tolist(), close=True, dxfattribs={"layer": layer})


def _label(msp: Any, text: str, xy: ArrayLike, layer: str) -> None:
    msp.add_text(text, height=TEXT_HEIGHT, dxfattribs={"layer": layer}).set_placement(
        tuple(np.asarray(xy, dtype=float)[:2])
    )


def site_plan_document(
    elements: Sequence[Element],
    stations: Iterable[Any] | None = None,
    platform_footprint: tuple[float, float] | None = None,
    anchors: Mapping[str, ArrayLike] | None = None,
    instrument: Any = None,
    control_points: Mapping[str, ArrayLike] | None = None,
) -> ezdxf.document.Drawing:
    """Build the site plan as an ezdxf document (see :func:`write_site_plan`)."""
    doc = ezdxf.new("R2010", setup=True, units=ezdxf.units.MM)
    doc.header["$MEASUREMENT"] = 1
    for name, colour in _LAYERS.items():
        doc.layers.add(name, color=colour)
    msp = doc.modelspace()

    blocks = [e for e in elements if e.type == "block" and e.extents is not None]
    if blocks:
        T = np.stack([e.T_world_element for e in blocks])
        ext = np.stack([np.asarray(e.extents, dtype=float) for e in blocks])
        fp = box_footprints(box_corners(T, ext))
        _add_polygon(msp, shapely.unary_union(fp), "FOOTPRINT")
        parts = np.array([e.part or "none" for e in blocks])
        placed: list[np.ndarray] = []
        for k, part in enumerate(sorted(set(parts.tolist()))):
            layer = f"PART_{part}".upper().replace(" ", "_")
            if layer not in doc.layers:
                doc.layers.add(layer, color=_PART_COLOURS[k % len(_PART_COLOURS)])
            union = shapely.unary_union(fp[parts == part])
            _add_polygon(msp, union, layer)
            at = np.asarray(union.representative_point().coords[0]) * MM
            # parts stacked on the same footprint: move the label down until it is free
            while any(np.linalg.norm(at - q) < 1.5 * TEXT_HEIGHT for q in placed):
                at = at - [0.0, 1.5 * TEXT_HEIGHT]
            placed.append(at)
            _label(msp, part, at, layer)

    for e in elements:
        if e.type != "print_path" or e.polyline is None or e.layer != 0:
            continue
        pts = (e.polyline @ e.T_world_element[:3, :3].T + e.T_world_element[:3, 3]) * MM
        extrude = np.asarray(e.attributes.get("extrude", np.ones(len(pts) - 1)), dtype=bool)
        # one polyline per run of extruding segments
        edges = np.flatnonzero(np.diff(np.concatenate(([0], extrude.astype(int), [0]))))
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            msp.add_polyline3d(pts[a : b + 1].tolist(), dxfattribs={"layer": "PRINT_PATH"})

    for e in elements:
        if e.type != "task_point":
            continue
        p = e.T_world_element[:3, 3] * MM
        msp.add_point(p.tolist(), dxfattribs={"layer": "TASK_POINTS"})
        msp.add_circle(p.tolist(), radius=25.0, dxfattribs={"layer": "TASK_POINTS"})
        _label(msp, f"{e.id} {e.attributes.get('action', '')}".strip(), p + 40.0, "TASK_POINTS")

    for station in stations or ():
        sid, T = _station_fields(station)
        o = T[:3, 3] * MM
        x = T[:3, 0] / max(np.linalg.norm(T[:2, 0]), 1e-12)
        msp.add_circle(o.tolist(), radius=60.0, dxfattribs={"layer": "STATIONS"})
        msp.add_line(o.tolist(), (o + 400.0 * x).tolist(), dxfattribs={"layer": "STATIONS"})
        _label(msp, sid, o + np.array([80.0, 80.0, 0.0]), "STATIONS")
        if platform_footprint is not None:
            length, width = platform_footprint
            local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * [length / 2, width / 2]
            corners = local @ T[:2, :2].T + T[:2, 3]
            msp.add_lwpolyline(
                (corners * MM).tolist(), close=True, dxfattribs={"layer": "PLATFORMS"}
            )

    for name, xyz in (anchors or {}).items():
        p = np.asarray(xyz, dtype=float) * MM
        msp.add_circle(p.tolist(), radius=50.0, dxfattribs={"layer": "UWB_ANCHORS"})
        _label(msp, f"{name} z={p[2] / MM:.2f}", p + 70.0, "UWB_ANCHORS")

    for name, xyz in _instrument_setups(instrument):
        p = xyz * MM
        tri = p[:2] + 120.0 * np.array([[0.0, 1.0], [-0.866, -0.5], [0.866, -0.5]])
        msp.add_lwpolyline(tri.tolist(), close=True, dxfattribs={"layer": "TOTAL_STATION"})
        _label(msp, name, p + np.array([150.0, 0.0, 0.0]), "TOTAL_STATION")

    for name, xyz in (control_points or {}).items():
        p = np.asarray(xyz, dtype=float) * MM
        msp.add_circle(p.tolist(), radius=80.0, dxfattribs={"layer": "CONTROL_POINTS"})
        for d in (np.array([80.0, 0.0, 0.0]), np.array([0.0, 80.0, 0.0])):
            msp.add_line((p - d).tolist(), (p + d).tolist(), dxfattribs={"layer": "CONTROL_POINTS"})
        _label(msp, f"{name} z={p[2] / MM:.2f}", p + 100.0, "CONTROL_POINTS")
    return doc


def write_site_plan(
    path: str | Path,
    elements: Sequence[Element],
    stations: Iterable[Any] | None = None,
    platform_footprint: tuple[float, float] | None = None,
    anchors: Mapping[str, ArrayLike] | None = None,
    instrument: Any = None,
    control_points: Mapping[str, ArrayLike] | None = None,
) -> Path:
    """Write the site plan DXF (millimetres, named layers; passes ``ezdxf`` audit).

    Parameters
    ----------
    path
        The DXF file to write.
    elements
        The design elements (world frame).
    stations
        Stations: objects with ``id`` and ``T_world_platform`` (4x4, metres) such
        as :class:`fabflow.tasks.plan.Station`, or mappings with those keys.
    platform_footprint
        Platform (length, width) in metres, drawn at every station.
    anchors
        UWB anchor positions in the world frame (metres) by name.
    instrument
        Total-station setup(s) in the world: one ``T_world_instrument`` (4x4) or
        position (3,), an (N, 3) array, or a mapping name -> pose or position.
    control_points
        Surveyed control points of the total station's free stationing (world, metres).

    Returns
    -------
    Path
        The file written.
    """
    doc = site_plan_document(
        elements, stations, platform_footprint, anchors, instrument, control_points
    )
    auditor = doc.audit()
    if auditor.has_errors:
        raise RuntimeError(f"site plan fails the DXF audit: {auditor.errors}")
    path = Path(path)
    doc.saveas(path)
    return path
