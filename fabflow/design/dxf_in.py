"""Read print-path contours from a DXF drawing.

Supported entities: LINE, LWPOLYLINE (with arc bulges), POLYLINE (2D and 3D, not
meshes), ARC, CIRCLE and SPLINE, on named layers. Curves are flattened to
polylines whose chords stay within ``flatten_tol`` of the curve; the pieces are
chained end to end into contours. Units come from the header variable
``$INSUNITS`` (millimetres when it is unset) unless given explicitly; the
returned contours are in metres, in the drawing's world coordinate system.

Problems the drawing causes raise :class:`~fabflow.errors.InputError` naming the
file and the entity handle or layer: a named layer that does not exist or holds
no supported entity, zero-length segments, an open contour where closed ones are
required, a contour crossing itself. Entities of other types on the chosen layers
are listed in a :class:`DxfWarning`.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import ezdxf
import numpy as np
import shapely
from ezdxf import units as ezunits

from fabflow.errors import InputError

SUPPORTED = ("LINE", "LWPOLYLINE", "POLYLINE", "ARC", "CIRCLE", "SPLINE")
ZERO_LENGTH = 1e-6
"""Segments shorter than this (metres) count as zero-length."""
PLAUSIBLE_SPAN = (0.005, 200.0)
"""Contours spanning less or more than this (metres) get a units warning."""
UNIT_CODES = {"in": 1, "ft": 2, "mm": 4, "cm": 5, "m": 6}


class DxfWarning(UserWarning):
    """Something in a DXF drawing was ignored (unsupported entities, missing units)."""


@dataclass(frozen=True)
class Contour:
    """One chained path from a drawing (metres, drawing frame).

    Attributes
    ----------
    points
        (N, 3) vertices; for a closed contour the last vertex equals the first.
    closed
        Whether the contour returns to its start.
    segment_handles
        (N - 1,) handle of the DXF entity each segment comes from.
    layer
        The DXF layer of the entities.
    """

    points: np.ndarray
    closed: bool
    segment_handles: np.ndarray
    layer: str

    @property
    def handles(self) -> list[str]:
        """The entity handles making up the contour, in path order, without repeats."""
        seen: dict[str, None] = {}
        for h in self.segment_handles.tolist():
            seen.setdefault(h, None)
        return list(seen)


def units_factor(doc: ezdxf.document.Drawing, units: str, source: str | Path) -> float:
    """Metres per drawing unit, from ``units`` or the header's ``$INSUNITS``."""
    if units != "auto":
        return ezunits.conversion_factor(UNIT_CODES[units], ezunits.M)
    code = int(doc.header.get("$INSUNITS", 0))
    if code == 0:
        warnings.warn(
            f"{source}: $INSUNITS is not set; reading the drawing as millimetres",
            DxfWarning,
            stacklevel=3,
        )
        return 1e-3
    try:
        return ezunits.conversion_factor(code, ezunits.M)
    except (KeyError, IndexError, ValueError):
        raise InputError(
            f"$INSUNITS = {code} is not a length unit fabflow knows", source, "HEADER"
        ) from None


def _zero_length_check(pts: np.ndarray, handle: str, source: str | Path, tol: float) -> None:
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    bad = np.flatnonzero(seg <= tol)
    if bad.size:
        raise InputError(
            f"zero-length segment between vertices {bad[0]} and {bad[0] + 1} "
            f"at ({pts[bad[0], 0]:.6g}, {pts[bad[0], 1]:.6g}) in drawing units",
            source,
            f"entity {handle}",
        )


def _entity_points(
    e: ezdxf.entities.DXFGraphic, flat: float, source: str | Path, tol: float
) -> tuple[np.ndarray, bool]:
    """Vertices (drawing units, WCS) of one supported entity and whether it is closed."""
    kind = e.dxftype()
    handle = e.dxf.handle
    if kind == "LINE":
        pts = np.array([e.dxf.start, e.dxf.end], dtype=float)
        _zero_length_check(pts, handle, source, tol)
        return pts, False
    if kind in ("ARC", "CIRCLE") and e.dxf.radius <= tol:
        raise InputError(f"{kind} with zero radius", source, f"entity {handle}")
    if kind == "ARC" and abs((e.dxf.end_angle - e.dxf.start_angle) % 360.0) <= 1e-9:
        raise InputError("ARC with zero sweep angle", source, f"entity {handle}")
    if kind == "LWPOLYLINE":
        raw = np.array([(x, y) for x, y, *_ in e.get_points("xy")], dtype=float)
        closed = bool(e.closed)
        if closed and len(raw) > 2 and np.linalg.norm(raw[-1] - raw[0]) <= tol:
            raw = raw[:-1]
        _zero_length_check(np.column_stack([raw, np.zeros(len(raw))]), handle, source, tol)
        if len(raw) < 2:
            raise InputError("LWPOLYLINE with fewer than two vertices", source, f"entity {handle}")
    if kind == "POLYLINE":
        if e.is_poly_face_mesh or e.is_polygon_mesh:
            raise InputError("POLYLINE meshes are not paths", source, f"entity {handle}")
        raw = np.array([v.dxf.location for v in e.vertices], dtype=float)
        closed = bool(e.is_closed)
        if closed and len(raw) > 2 and np.linalg.norm(raw[-1] - raw[0]) <= tol:
            raw = raw[:-1]
        if len(raw) < 2:
            raise InputError("POLYLINE with fewer than two vertices", source, f"entity {handle}")
        _zero_length_check(raw, handle, source, tol)
    if kind == "SPLINE":
        pts = np.array(list(e.construction_tool().flattening(flat, segments=8)), dtype=float)
        closed = bool(e.closed) or (len(pts) > 2 and np.linalg.norm(pts[-1] - pts[0]) <= tol)
    elif kind in ("ARC", "CIRCLE"):
        pts = np.array(list(e.flattening(flat)), dtype=float)
        closed = kind == "CIRCLE"
    else:
        # polylines: exact arcs for bulges, through their LINE and ARC sub-entities
        parts = [
            np.array(
                [v.dxf.start, v.dxf.end] if v.dxftype() == "LINE" else list(v.flattening(flat)),
                dtype=float,
            )
            for v in e.virtual_entities()
        ]
        pts = np.vstack([parts[0]] + [q[1:] for q in parts[1:]])
    if len(pts) >= 2:
        keep = np.concatenate(([True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > tol))
        pts = pts[keep]
    if len(pts) < 2 or np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)) <= tol:
        raise InputError(f"{kind} of zero length", source, f"entity {handle}")
    if closed and np.linalg.norm(pts[-1] - pts[0]) > tol:
        pts = np.vstack([pts, pts[:1]])
    elif closed:
        pts[-1] = pts[0]
    return pts, closed


def _chain(
    pieces: list[tuple[np.ndarray, bool, str]], tol: float
) -> list[tuple[np.ndarray, bool, np.ndarray]]:
    """Join open pieces whose ends meet (within ``tol``) into contours.

    Contours come out in the order of their first piece in ``pieces``.
    """
    out: list[tuple[int, np.ndarray, bool, np.ndarray]] = []
    open_pieces = []
    first = []
    for k, (pts, closed, handle) in enumerate(pieces):
        handles = np.full(len(pts) - 1, handle, dtype=object)
        if closed:
            out.append((k, pts, True, handles))
        else:
            open_pieces.append((pts, handles))
            first.append(k)
    used = np.zeros(len(open_pieces), dtype=bool)
    starts = np.array([p[0][0] for p in open_pieces]).reshape(-1, 3)
    ends = np.array([p[0][-1] for p in open_pieces]).reshape(-1, 3)
    for i in range(len(open_pieces)):
        if used[i]:
            continue
        used[i] = True
        pts, handles = open_pieces[i]
        for _ in range(2):  # grow at the end, then (reversed) at the other end
            while True:
                d_s = np.linalg.norm(starts - pts[-1], axis=1)
                d_e = np.linalg.norm(ends - pts[-1], axis=1)
                d_s[used], d_e[used] = np.inf, np.inf
                j_s, j_e = int(np.argmin(d_s)), int(np.argmin(d_e))
                if d_s[j_s] <= tol and d_s[j_s] <= d_e[j_e]:
                    nxt, nh = open_pieces[j_s]
                    used[j_s] = True
                elif d_e[j_e] <= tol:
                    nxt, nh = open_pieces[j_e][0][::-1], open_pieces[j_e][1][::-1]
                    used[j_e] = True
                else:
                    break
                pts = np.vstack([pts, nxt[1:]])
                handles = np.concatenate([handles, nh])
                if np.linalg.norm(pts[-1] - pts[0]) <= tol:
                    break
            if np.linalg.norm(pts[-1] - pts[0]) <= tol and len(pts) > 2:
                pts[-1] = pts[0]
                break
            pts, handles = pts[::-1].copy(), handles[::-1].copy()
        closed = len(pts) > 3 and np.linalg.norm(pts[-1] - pts[0]) <= tol
        out.append((first[i], pts, bool(closed), handles))
    out.sort(key=lambda item: item[0])
    return [item[1:] for item in out]


def _self_intersection(points: np.ndarray, closed: bool) -> tuple[int, int] | None:
    """Indices of two non-adjacent segments that touch, or ``None``."""
    n = len(points) - 1
    if n < 3:
        return None
    segs = shapely.linestrings(np.stack([points[:-1, :2], points[1:, :2]], axis=1))
    tree = shapely.STRtree(segs)
    i, j = tree.query(segs, predicate="intersects")
    keep = j > i + 1
    if closed:
        keep &= ~((i == 0) & (j == n - 1))
    if not keep.any():
        return None
    k = int(np.flatnonzero(keep)[0])
    return int(i[k]), int(j[k])


def read_dxf_contours(
    path: str | Path,
    layers: Sequence[str] = (),
    units: str = "auto",
    require_closed: bool = True,
    flatten_tol: float = 5e-5,
    join_tol: float = 1e-4,
) -> list[Contour]:
    """Read the path contours on the named layers of a DXF file.

    Parameters
    ----------
    path
        The DXF file.
    layers
        Layer names to read (case-insensitive, as in CAD programs); all layers when empty.
    units
        ``"auto"`` (from ``$INSUNITS``) or one of ``m``, ``cm``, ``mm``, ``in``, ``ft``.
    require_closed
        Raise for a contour that does not return to its start.
    flatten_tol
        Largest distance between a curve and its flattened chords (metres).
    join_tol
        Largest gap between entity ends that still joins them (metres).

    Returns
    -------
    list of Contour
        Contours in metres, drawing frame, in the order their first entity appears.
    """
    path = Path(path)
    try:
        doc = ezdxf.readfile(path)
    except OSError as exc:
        raise InputError(f"cannot read DXF file: {exc}", path) from None
    except ezdxf.DXFError as exc:
        raise InputError(f"not a valid DXF file: {exc}", path) from None
    factor = units_factor(doc, units, path)
    msp = doc.modelspace()
    all_layers = sorted({e.dxf.layer for e in msp})
    wanted = {name.casefold() for name in layers}
    if wanted:
        known = {name.casefold() for name in all_layers} | {
            layer.dxf.name.casefold() for layer in doc.layers
        }
        missing = [name for name in layers if name.casefold() not in known]
        if missing:
            raise InputError(
                f"the drawing has no layer {missing[0]!r} "
                f"(its layers with entities: {', '.join(all_layers) or 'none'})",
                path,
                f"layer {missing[0]}",
            )
    pieces_by_layer: dict[str, list[tuple[np.ndarray, bool, str]]] = {}
    unsupported: list[str] = []
    for e in msp:
        layer = e.dxf.layer
        if wanted and layer.casefold() not in wanted:
            continue
        if e.dxftype() not in SUPPORTED:
            unsupported.append(f"{e.dxftype()} {e.dxf.handle}")
            continue
        pts, closed = _entity_points(e, flatten_tol / factor, path, ZERO_LENGTH / factor)
        pieces_by_layer.setdefault(layer, []).append((pts * factor, closed, e.dxf.handle))
    if unsupported:
        shown = ", ".join(unsupported[:20]) + (" ..." if len(unsupported) > 20 else "")
        warnings.warn(
            f"{path}: ignored {len(unsupported)} unsupported entities ({shown}); "
            f"supported are {', '.join(SUPPORTED)}",
            DxfWarning,
            stacklevel=2,
        )
    for name in layers:
        if not any(k.casefold() == name.casefold() for k in pieces_by_layer):
            raise InputError(
                f"layer {name!r} holds no {', '.join(SUPPORTED)} entity", path, f"layer {name}"
            )
    if not pieces_by_layer:
        raise InputError(f"the drawing holds no {', '.join(SUPPORTED)} entity", path)

    contours: list[Contour] = []
    for layer, pieces in pieces_by_layer.items():
        for pts, closed, handles in _chain(pieces, join_tol):
            c = Contour(pts, closed, handles, layer)
            if require_closed and not closed:
                p0, p1 = pts[0] / factor, pts[-1] / factor
                raise InputError(
                    f"open contour where a closed one is required: it starts at "
                    f"({p0[0]:.6g}, {p0[1]:.6g}) and ends at ({p1[0]:.6g}, {p1[1]:.6g}) "
                    f"(drawing units), entities {', '.join(c.handles)}",
                    path,
                    f"entity {handles[0]}",
                )
            crossing = _self_intersection(pts, closed)
            if crossing is not None:
                a, b = crossing
                at = pts[a] / factor
                raise InputError(
                    f"contour on layer {layer!r} crosses itself near ({at[0]:.6g}, {at[1]:.6g}) "
                    f"(drawing units): entities {handles[a]} and {handles[b]}",
                    path,
                    f"entity {handles[a]}",
                )
            contours.append(c)
    span = np.ptp(np.vstack([c.points for c in contours])[:, :2], axis=0).max()
    if not PLAUSIBLE_SPAN[0] <= span <= PLAUSIBLE_SPAN[1]:
        warnings.warn(
            f"{path}: the contours span {span:.4g} m, which is unusual for a print path; "
            f"check the drawing units ($INSUNITS or the project's 'units')",
            DxfWarning,
            stacklevel=2,
        )
    return contours
