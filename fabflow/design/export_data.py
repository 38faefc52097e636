"""What an export holds, checked once for every writer (Rhino .3dm, COMPAS JSON).

The writers (:mod:`fabflow.design.rhino_out`, :mod:`fabflow.design.compas_out`)
take plain data: the elements, the plan's stations as :class:`StationRecord`,
UWB anchors and instrument set-ups as name -> position, simulated as-built poses
as element id -> 4x4. :func:`export_content` checks it all together (ids,
finite numbers, rigid poses) so that a writer never writes NaN, infinity or a
half-checked file, and :func:`element_user_text` gives the user text of
:mod:`fabflow.design.exchange` that an element carries in Rhino.

Frames: everything is in the world frame, metres.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from fabflow.design import exchange
from fabflow.design.elements import Element
from fabflow.errors import InputError
from fabflow.files import strict_json
from fabflow.json_format import json_text

RIGID_TOLERANCE = 1e-6
"""Largest entry of ``|R^T R - I|`` (and of ``|det R - 1|``) in a pose that is written."""


@dataclass(frozen=True, eq=False)
class StationRecord:
    """A station of the plan, as an export shows it.

    Attributes
    ----------
    id
        Station id (``"S1"``).
    T_world_platform
        4x4 platform pose in the world (metres; origin on the ground, z up).
    footprint
        ``(K, 3)`` corners of the platform's outline at ground level (world,
        metres), in order, the first not repeated at the end.
    elements
        Ids of the elements built from this station, in build order.
    """

    id: str
    T_world_platform: np.ndarray
    footprint: np.ndarray
    elements: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class ExportContent:
    """Checked export data (see :func:`export_content`).

    Attributes
    ----------
    elements
        The elements, in the order given.
    stations
        The stations, in the order given.
    station_of
        Element id -> id of the station that builds it (absent: unplanned).
    anchors, setups
        Name -> ``(3,)`` position (world, metres).
    as_built
        Element id -> ``(4, 4)`` simulated as-built pose (world, metres).
    """

    elements: list[Element]
    stations: list[StationRecord] = field(default_factory=list)
    station_of: dict[str, str] = field(default_factory=dict)
    anchors: dict[str, np.ndarray] = field(default_factory=dict)
    setups: dict[str, np.ndarray] = field(default_factory=dict)
    as_built: dict[str, np.ndarray] = field(default_factory=dict)


def _poses(poses: list[np.ndarray], names: list[str], what: str) -> None:
    """Refuse poses that are not finite rigid 4x4 transforms (checked at once)."""
    if not poses:
        return
    shapes = [i for i, T in enumerate(poses) if T.shape != (4, 4)]
    if shapes:
        raise InputError(f"{what} {names[shapes[0]]}: a pose must be 4x4")
    T = np.stack(poses)
    bad = ~np.isfinite(T).all(axis=(1, 2))
    if bad.any():
        raise InputError(f"{what} {names[int(np.argmax(bad))]}: its pose is not finite")
    R = T[:, :3, :3]
    gram = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    det = np.abs(np.linalg.det(R) - 1.0)
    row = np.abs(T[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    bad = (gram > RIGID_TOLERANCE) | (det > RIGID_TOLERANCE) | (row > 0.0)
    if bad.any():
        raise InputError(f"{what} {names[int(np.argmax(bad))]}: its pose is not a rigid transform")


def _points(points: Mapping[str, ArrayLike] | None, what: str) -> dict[str, np.ndarray]:
    out = {}
    for name, xyz in (points or {}).items():
        p = np.asarray(xyz, dtype=float)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise InputError(f"{what} {name}: its position must be 3 finite numbers (metres)")
        out[str(name)] = p
    return out


def _geometry(e: Element) -> None:
    """Refuse an element whose box or polyline is not finite."""
    if e.extents is not None:
        ext = np.asarray(e.extents, dtype=float)
        if ext.shape != (3,) or not np.isfinite(ext).all() or (ext <= 0).any():
            raise InputError(f"element {e.id}: extents must be 3 positive finite sizes (metres)")
    if e.polyline is not None:
        pts = np.asarray(e.polyline, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts) or not np.isfinite(pts).all():
            raise InputError(f"element {e.id}: its polyline must be finite (N, 3) points")


def export_content(
    elements: Sequence[Element],
    stations: Sequence[StationRecord] = (),
    anchors: Mapping[str, ArrayLike] | None = None,
    setups: Mapping[str, ArrayLike] | None = None,
    as_built: Mapping[str, ArrayLike] | None = None,
) -> ExportContent:
    """Check what an export is to hold.

    Parameters
    ----------
    elements
        The elements (world frame, metres); ids unique.
    stations
        The plan's stations; each element is built from one station at most.
    anchors, setups
        UWB anchors and total station set-ups: name -> position (world, metres).
    as_built
        Simulated as-built pose (4x4, world, metres) by element id.

    Raises
    ------
    InputError
        For an id used twice, a pose that is not a finite rigid transform, a
        box or polyline that is not finite, a station footprint that is not
        finite ``(K >= 3, 3)`` corners, a station or as-built pose naming an
        element not exported, or an element named by two stations.
    """
    elements = list(elements)
    ids = [e.id for e in elements]
    known = set(ids)
    if len(known) != len(ids):
        dup = next(i for i, n in Counter(ids).items() if n > 1)
        raise InputError(f"element id {dup!r} is used twice")
    _poses([np.asarray(e.T_world_element, dtype=float) for e in elements], ids, "element")
    for e in elements:
        _geometry(e)
    station_ids = [s.id for s in stations]
    if len(set(station_ids)) != len(station_ids):
        raise InputError("a station id is used twice")
    _poses([np.asarray(s.T_world_platform, dtype=float) for s in stations], station_ids, "station")
    station_of: dict[str, str] = {}
    for s in stations:
        fp = np.asarray(s.footprint, dtype=float)
        if fp.ndim != 2 or fp.shape[1] != 3 or len(fp) < 3 or not np.isfinite(fp).all():
            raise InputError(f"station {s.id}: its footprint must be finite (K >= 3, 3) corners")
        for eid in s.elements:
            if eid not in known:
                raise InputError(f"station {s.id} builds element {eid!r}, which is not exported")
            if station_of.setdefault(eid, s.id) != s.id:
                raise InputError(
                    f"element {eid} is built from stations {station_of[eid]} and {s.id}"
                )
    built = {str(k): np.asarray(v, dtype=float) for k, v in (as_built or {}).items()}
    unknown = next((k for k in built if k not in known), None)
    if unknown is not None:
        raise InputError(f"as-built pose of element {unknown!r}, which is not exported")
    _poses(list(built.values()), list(built), "as-built element")
    return ExportContent(
        elements=elements,
        stations=list(stations),
        station_of=station_of,
        anchors=_points(anchors, "anchor"),
        setups=_points(setups, "set-up"),
        as_built=built,
    )


def frame_text(T: ArrayLike) -> str:
    """A pose as the text of :data:`~fabflow.design.exchange.KEY_FRAME`.

    The 16 numbers row by row as a JSON list, each written as the shortest
    text that reads back to the same float: :func:`frame_from_text` returns the
    same bits.
    """
    return json_text(np.asarray(T, dtype=float).reshape(16).tolist(), indent=None).strip()


def frame_from_text(text: str) -> np.ndarray:
    """Inverse of :func:`frame_text`: the ``(4, 4)`` pose.

    Raises
    ------
    ValueError
        When ``text`` is not a JSON list of 16 finite numbers.
    """
    message = f"{exchange.KEY_FRAME} must be a JSON list of 16 finite numbers"
    try:
        values = np.asarray(strict_json(text), dtype=float)
    except (ValueError, TypeError):
        raise ValueError(message) from None
    if values.shape != (16,) or not np.isfinite(values).all():
        raise ValueError(message)
    return values.reshape(4, 4)


def element_user_text(e: Element, station: str | None) -> dict[str, str]:
    """The user text an exported element carries (keys of :mod:`fabflow.design.exchange`).

    Keys without a value are left out (Rhino drops empty user text): the part
    of an element without one, the supports of one that rests on the ground,
    the station of an unplanned element, the extents of an element that is not
    a box.
    """
    text = {
        exchange.KEY_ID: e.id,
        exchange.KEY_TYPE: e.type,
        exchange.KEY_LAYER: str(int(e.layer)),
        exchange.KEY_PART: "" if e.part is None else str(e.part),
        exchange.KEY_SUPPORTS: ",".join(e.supports),
        exchange.KEY_ROBOT_BUILT: "true" if e.robot_built else "false",
        exchange.KEY_FRAME: frame_text(e.T_world_element),
        exchange.KEY_STATION: station or "",
        exchange.KEY_ATTRIBUTES: json_text(e.attributes, indent=None).strip(),
    }
    if e.extents is not None:
        text[exchange.KEY_EXTENTS] = json_text(
            np.asarray(e.extents, dtype=float).tolist(), indent=None
        ).strip()
    return {k: v for k, v in text.items() if v}


def platform_footprints(T_world_platform: ArrayLike, size: tuple[float, float]) -> np.ndarray:
    """Corners of platform outlines at ground level (world, metres), counter-clockwise.

    Parameters
    ----------
    T_world_platform
        ``(S, 4, 4)`` platform poses (origin on the ground, z up; metres).
    size
        The platform's plan rectangle: length along its x, width along its y
        (metres), centred on its origin.

    Returns
    -------
    numpy.ndarray
        ``(S, 4, 3)`` corners: the rectangle in the platform's ground plane.
    """
    T = np.asarray(T_world_platform, dtype=float).reshape(-1, 4, 4)
    hx, hy = 0.5 * float(size[0]), 0.5 * float(size[1])
    local = np.array([[hx, hy, 0.0], [-hx, hy, 0.0], [-hx, -hy, 0.0], [hx, -hy, 0.0]])
    return np.einsum("sij,kj->ski", T[:, :3, :3], local) + T[:, None, :3, 3]


def world_polyline(e: Element, T_world_element: np.ndarray | None = None) -> np.ndarray:
    """``(N, 3)`` points of a print path in the world (metres).

    At the element's own pose, or at ``T_world_element`` (an as-built pose).
    """
    T = np.asarray(e.T_world_element if T_world_element is None else T_world_element, dtype=float)
    return np.asarray(e.polyline, dtype=float) @ T[:3, :3].T + T[:3, 3]
