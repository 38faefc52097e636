"""Read print-path contours from a DXF drawing.

Supported entities: LINE, LWPOLYLINE (with arc bulges), POLYLINE (2D and 3D, not
meshes), ARC, CIRCLE and SPLINE, on named layers. Curves are flattened to
polylines whose chords stay within ``flatten_tol`` of the curve; the pieces are
chained end to end into contours. Units come from the header variable
``$INSUNITS`` (millimetres when it is unset) unless given explicitly; the
returned contours are in metres, in the drawing's world coordinate system.

Problems the drawing causes raise :class:`~fabflow.errors.InputError` naming the
file and the entity handle or layer: a file that is not a DXF drawing, a named
layer that does not exist or holds no supported entity, zero-length segments, an
open contour where closed ones are required, a contour crossing itself.
Entities of other types on the chosen layers are listed in a :class:`DxfWarning`.

The work a drawing can ask for is bounded before it is done: the file is a
regular file of at most :data:`MAX_DXF_BYTES` (:func:`fabflow.files.input_file`),
with at most :data:`MAX_DXF_ENTITIES` entities, :data:`MAX_PATH_ENTITIES` of
them on the chosen layers; every coordinate is finite and within
:data:`MAX_DXF_COORDINATE_M`, an entity spans at most :data:`MAX_ENTITY_SIZE_M`,
a spline has at most :data:`MAX_SPLINE_POINTS` points, and the flattened
contours at most :data:`MAX_PATH_VERTICES` vertices (estimated per entity before
it is flattened).
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
from fabflow.files import input_file, show

SUPPORTED = ("LINE", "LWPOLYLINE", "POLYLINE", "ARC", "CIRCLE", "SPLINE")
ZERO_LENGTH = 1e-6
"""Segments shorter than this (metres) count as zero-length."""
PLAUSIBLE_SPAN = (0.005, 200.0)
"""Contours spanning less or more than this (metres) get a units warning."""
UNIT_CODES = {"in": 1, "ft": 2, "mm": 4, "cm": 5, "m": 6}
MAX_DXF_BYTES = 64 * 2**20
"""Largest DXF file read (bytes); a drawing of print paths takes kilobytes."""
MAX_DXF_ENTITIES = 200_000
"""Most entities the drawing's model space may hold."""
MAX_PATH_ENTITIES = 10_000
"""Most supported entities on the chosen layers (they are chained pairwise)."""
MAX_PATH_VERTICES = 500_000
"""Most vertices of all contours after flattening at ``flatten_tol``."""
MAX_SPLINE_POINTS = 1000
"""Most control or fit points of one spline."""
MAX_DXF_COORDINATE_M = 1e7
"""Largest magnitude of a coordinate (metres, after the drawing units)."""
MAX_ENTITY_SIZE_M = 1e4
"""Largest span of one entity (metres): its extent, or the diameter of an arc."""
_EZDXF_FAILURES = (
    ezdxf.DXFError,
    ValueError,
    TypeError,
    LookupError,
    AttributeError,
    ArithmeticError,
    StopIteration,
    AssertionError,
    RecursionError,
)
"""What ezdxf raises on a damaged file: its own errors and whatever its parser meets."""


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
    try:
        code = int(doc.header.get("$INSUNITS", 0))
    except (TypeError, ValueError, OverflowError):
        raise InputError("$INSUNITS is not an integer", source, "HEADER") from None
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


def _arc_segments(radius: np.ndarray, sweep: np.ndarray, sagitta: float) -> np.ndarray:
    """Chords needed to keep arcs of ``radius`` and ``sweep`` (rad) within ``sagitta``."""
    r = np.maximum(np.abs(radius), 1e-300)
    step = 2.0 * np.arccos(np.clip(1.0 - sagitta / r, -1.0, 1.0))
    return np.ceil(np.abs(sweep) / np.maximum(step, 1e-12)) + 1.0


def _bulge_arcs(xy: np.ndarray, bulge: np.ndarray, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Radius and sweep of the arc segments of a polyline with bulges (drawing units, rad)."""
    nxt = np.roll(xy, -1, axis=0) if closed else xy[1:]
    b = bulge if closed else bulge[:-1]
    chord = np.linalg.norm(nxt - xy[: len(nxt)], axis=1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        radius = np.where(b != 0, chord * (1.0 + b * b) / (4.0 * np.abs(b)), 0.0)
    return np.minimum(radius, 1e300), 4.0 * np.arctan(np.abs(b))


def entity_budget(
    e: ezdxf.entities.DXFGraphic, sagitta: float, factor: float, source: str | Path
) -> float:
    """Check an entity's numbers and estimate how many vertices it flattens to.

    Parameters
    ----------
    e
        A supported entity.
    sagitta
        Largest distance between a curve and its chords (drawing units).
    factor
        Metres per drawing unit.
    source
        The file, named in errors.

    Returns
    -------
    float
        The estimated vertex count after flattening (a spline: 64 per point).

    Raises
    ------
    InputError
        A value that is not finite, a coordinate beyond :data:`MAX_DXF_COORDINATE_M`,
        an entity spanning more than :data:`MAX_ENTITY_SIZE_M` (an arc: its
        diameter), a spline with more than :data:`MAX_SPLINE_POINTS` points;
        naming the entity handle.
    """
    kind = e.dxftype()
    where = f"entity {_handle(e)}"
    with np.errstate(invalid="ignore", over="ignore"):  # checked below: finite and bounded
        box, estimate = _entity_box(e, kind, sagitta, source, where)
        finite = bool(np.all(np.isfinite(box))) and bool(np.isfinite(estimate))
        size = np.abs(box).max() if finite and len(box) else 0.0
        span = np.ptp(box, axis=0).max() if finite and len(box) else 0.0
    if not finite:
        raise InputError(f"{kind} has a value that is not finite", source, where)
    if size * factor > MAX_DXF_COORDINATE_M:
        raise InputError(
            f"{kind} lies beyond {MAX_DXF_COORDINATE_M:g} m from the origin", source, where
        )
    if span * factor > MAX_ENTITY_SIZE_M:
        raise InputError(
            f"{kind} spans more than {MAX_ENTITY_SIZE_M:g} m (check the drawing units)",
            source,
            where,
        )
    return estimate


def _entity_box(
    e: ezdxf.entities.DXFGraphic, kind: str, sagitta: float, source: str | Path, where: str
) -> tuple[np.ndarray, float]:
    """Points bounding a supported entity (drawing units) and its flattened vertex estimate."""
    estimate = 2.0
    if kind == "LINE":
        box = np.array([e.dxf.start, e.dxf.end], dtype=float)
    elif kind in ("ARC", "CIRCLE"):
        c = np.asarray(e.dxf.center, dtype=float)
        r = float(e.dxf.radius)
        angles = (0.0, 360.0) if kind == "CIRCLE" else (e.dxf.start_angle, e.dxf.end_angle)
        if not np.all(np.isfinite(angles)):
            raise InputError(f"{kind} angles are not finite", source, where)
        box = c + np.array([[-r, -r, 0.0], [r, r, 0.0]])
        sweep = 2 * np.pi if kind == "CIRCLE" else np.radians((angles[1] - angles[0]) % 360.0)
        estimate = float(_arc_segments(np.array([r]), np.array([sweep]), sagitta)[0])
    elif kind == "SPLINE":
        parts = [np.asarray(e.control_points, dtype=float), np.asarray(e.fit_points, dtype=float)]
        n = sum(len(q) for q in parts)
        if n > MAX_SPLINE_POINTS:
            raise InputError(
                f"SPLINE with {n} points, more than {MAX_SPLINE_POINTS}", source, where
            )
        box = np.vstack([q.reshape(-1, 3) for q in parts]) if n else np.zeros((0, 3))
        estimate = 64.0 * n
    else:
        box, estimate = _polyline_box(e, sagitta)
    return box, estimate


def _polyline_box(e: ezdxf.entities.DXFGraphic, sagitta: float) -> tuple[np.ndarray, float]:
    """Points bounding a polyline and its bulge arcs (drawing units), and its vertex estimate.

    NaN in the points stands for a value that is not finite (a bulge included).
    """
    if e.dxftype() == "LWPOLYLINE":
        n = len(e)
        if n > MAX_PATH_VERTICES:
            return np.zeros((0, 3)), float(n)
        raw = np.array([tuple(v) for v in e.get_points("xyb")], dtype=float).reshape(-1, 3)
        pts = np.c_[raw[:, :2], np.zeros(n)]
        bulge, closed = raw[:, 2], bool(e.closed)
    else:
        n = len(e.vertices)
        if n > MAX_PATH_VERTICES:
            return np.zeros((0, 3)), float(n)
        pts = np.array([v.dxf.location for v in e.vertices], dtype=float).reshape(-1, 3)
        bulge = np.array([v.dxf.bulge for v in e.vertices], dtype=float)
        closed = bool(e.is_closed)
    if not np.all(np.isfinite(bulge)):
        return np.full((1, 3), np.nan), float(n)
    if n < 2 or not np.all(np.isfinite(pts)):
        return pts, float(n)
    radius, sweep = _bulge_arcs(pts[:, :2], bulge, closed)
    arcs = radius > 0
    starts = pts[: len(radius)][arcs]
    reach = 2.0 * radius[arcs, None] * np.array([[1.0, 1.0, 0.0]])
    box = np.vstack([pts, starts - reach, starts + reach])
    return box, float(n) + float(np.sum(_arc_segments(radius[arcs], sweep[arcs], sagitta)))


def _handle(e: ezdxf.entities.DXFGraphic) -> str:
    """The entity's handle, shortened (it comes from the file)."""
    return str(e.dxf.get("handle", "?"))[:16]


def _reason(exc: BaseException) -> str:
    """A short reason from an ezdxf error (its text may quote the file)."""
    text = str(exc) if isinstance(exc, ezdxf.DXFError) else type(exc).__name__
    return text if len(text) <= 100 else text[:100] + "..."


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
    input_file(path, "DXF drawing", MAX_DXF_BYTES)
    try:
        doc = ezdxf.readfile(path)
    except OSError as exc:  # ezdxf's own for a file that does not look like DXF
        what = f"cannot read DXF file: {exc.strerror}" if exc.strerror else "not a valid DXF file"
        raise InputError(what, path) from None
    except _EZDXF_FAILURES as exc:
        raise InputError(f"not a valid DXF file ({_reason(exc)})", path) from None
    factor = units_factor(doc, units, path)
    msp = doc.modelspace()
    if len(msp) > MAX_DXF_ENTITIES:
        raise InputError(
            f"the drawing has {len(msp)} entities, more than the {MAX_DXF_ENTITIES} fabflow reads",
            path,
        )
    try:
        entity_layers = [(e, str(e.dxf.layer)) for e in msp]
        table_layers = {str(layer.dxf.name).casefold() for layer in doc.layers}
    except _EZDXF_FAILURES as exc:
        raise InputError(f"not a valid DXF file ({_reason(exc)})", path) from None
    all_layers = sorted({layer for _, layer in entity_layers})
    wanted = {name.casefold() for name in layers}
    if wanted:
        known = {name.casefold() for name in all_layers} | table_layers
        missing = [name for name in layers if name.casefold() not in known]
        if missing:
            shown = ", ".join(show(name, 30) for name in all_layers[:12])
            raise InputError(
                f"the drawing has no layer {missing[0]!r} (its layers with entities: "
                f"{shown + (', ...' if len(all_layers) > 12 else '') or 'none'})",
                path,
                f"layer {missing[0]}",
            )
    pieces_by_layer: dict[str, list[tuple[np.ndarray, bool, str]]] = {}
    unsupported: list[str] = []
    n_entities, n_vertices = 0, 0
    sagitta, tol = flatten_tol / factor, ZERO_LENGTH / factor
    for e, layer in entity_layers:
        if wanted and layer.casefold() not in wanted:
            continue
        if e.dxftype() not in SUPPORTED:
            unsupported.append(f"{e.dxftype()} {_handle(e)}")
            continue
        n_entities += 1
        if n_entities > MAX_PATH_ENTITIES:
            raise InputError(
                f"more than {MAX_PATH_ENTITIES} entities on the chosen layers",
                path,
                f"entity {_handle(e)}",
            )
        try:
            n_vertices += entity_budget(e, sagitta, factor, path)
            if n_vertices > MAX_PATH_VERTICES:
                raise InputError(
                    f"the contours would take more than {MAX_PATH_VERTICES} vertices at a "
                    f"flattening tolerance of {flatten_tol:g} m",
                    path,
                    f"entity {_handle(e)}",
                )
            pts, closed = _entity_points(e, sagitta, path, tol)
        except _EZDXF_FAILURES as exc:
            raise InputError(
                f"cannot read this {e.dxftype()} ({_reason(exc)})", path, f"entity {_handle(e)}"
            ) from None
        pieces_by_layer.setdefault(layer, []).append((pts * factor, closed, _handle(e)))
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
