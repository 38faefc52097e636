"""Print paths: layers of contours, tool frames and constant-speed Hermite sampling.

A printed layer is one polyline (the *waypoints*) in its element frame, with a
flag per segment telling whether the extruder is on (printing a contour) or off
(travelling between contours). The path of the tool between waypoints is a
cubic Hermite curve whose tangent at every waypoint is the bisector of the two
adjacent segment directions (so the tangent is continuous), sampled at a fixed
rate (100 Hz) at constant tool speed, as in the excavator printing paper
(seeds 000, section IV-B).

The Hermite curve of a segment of length ``d`` whose end tangents make angles
``a0`` and ``a1`` with the chord stays within ``4/27 * d * (sin a0 + sin a1)`` of
the chord. Waypoints are added on the segments next to every bend until that
bound is below ``tol`` everywhere, so the sampled path stays within ``tol`` of
the drawn polyline (0.25 mm by default, half the allowed 0.5 mm).

Tool frames: z axis pointing down (against the layer's up axis), x along the
path, y = z cross x.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fabflow.design.dxf_in import Contour, read_dxf_contours
from fabflow.design.elements import Element
from fabflow.design.specs import PrintPathSpec
from fabflow.errors import InputError
from fabflow.transforms.se3 import make_T

if TYPE_CHECKING:
    import trimesh

_BOUND = 4.0 / 27.0
FILLET_MIN_DEG = 15.0
"""Corners turning more than this are filleted (smaller bends: bisector tangents)."""
FILLET_MAX_DEG = 150.0
"""Corners turning more than this (near reversals) keep a waypoint at the vertex."""
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(4)
_TABLE = 16


@dataclass(frozen=True)
class LayerPath:
    """The waypoints of one printed layer.

    Attributes
    ----------
    points
        (N, 3) waypoints (metres) in the layer's frame.
    extrude
        (N - 1,) whether the extruder is on along each segment.
    """

    points: np.ndarray
    extrude: np.ndarray

    @property
    def print_length(self) -> float:
        """Length of the extruding segments (metres)."""
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        return float(seg[self.extrude].sum())

    @property
    def travel_length(self) -> float:
        """Length of the travel segments (metres)."""
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        return float(seg[~self.extrude].sum())


@dataclass(frozen=True)
class SampledPath:
    """A path sampled at a fixed rate at constant speed.

    Attributes
    ----------
    t
        (M,) sample times (seconds), ``t[k] = k / rate``; the last sample is the
        path's end, reached after a shorter final step.
    points
        (M, 3) tool positions (metres) in the path's frame.
    tangents
        (M, 3) unit tangents (direction of travel).
    extrude
        (M,) whether the extruder is on at each sample.
    max_deviation
        Largest distance of a sample from the waypoint polyline (metres).
    length
        Length of the sampled curve (metres).
    """

    t: np.ndarray
    points: np.ndarray
    tangents: np.ndarray
    extrude: np.ndarray
    max_deviation: float
    length: float


def tool_frames(
    points: np.ndarray, tangents: np.ndarray, up: np.ndarray | None = None
) -> np.ndarray:
    """Tool frames along a path: z down (against ``up``), x along the path.

    Parameters
    ----------
    points
        (N, 3) tool positions (metres).
    tangents
        (N, 3) directions of travel (need not be unit length).
    up
        The up direction of the frame the points are in; (0, 0, 1) by default.

    Returns
    -------
    numpy.ndarray
        (N, 4, 4) poses ``T_frame_tool``. Where the tangent is vertical the x
        axis falls back to the frame's x axis.
    """
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=float)
    z = -up / np.linalg.norm(up)
    x = np.asarray(tangents, dtype=float) - np.outer(np.asarray(tangents) @ z, z)
    norm = np.linalg.norm(x, axis=1)
    flat = norm < 1e-12
    if flat.any():
        fallback = np.array([1.0, 0.0, 0.0]) - z[0] * z
        x[flat] = fallback
        norm[flat] = np.linalg.norm(fallback)
    x /= norm[:, None]
    y = np.cross(np.broadcast_to(z, x.shape), x)
    R = np.stack([x, y, np.broadcast_to(z, x.shape)], axis=2)
    return make_T(R, np.asarray(points, dtype=float))


def polyline_tangents(points: np.ndarray) -> np.ndarray:
    """Unit tangents at the vertices of a polyline: bisectors of adjacent segments.

    At a reversal (the two segments point in opposite directions) the tangent is
    perpendicular to the segment in the xy plane (or any perpendicular when vertical).
    Zero-length segments take the direction of their neighbour.
    """
    d = np.diff(points, axis=0)
    norm = np.linalg.norm(d, axis=1)
    ok = norm > 1e-12
    if not ok.any():
        raise ValueError("a path needs two distinct waypoints")
    # a zero-length segment takes the direction of the nearest earlier (else later) one
    idx = np.maximum.accumulate(np.where(ok, np.arange(len(d)), -1))
    idx[idx < 0] = np.flatnonzero(ok)[0]
    d = d[idx] / norm[idx][:, None]
    m = np.empty_like(points, dtype=float)
    m[0], m[-1] = d[0], d[-1]
    s = d[:-1] + d[1:]
    norm = np.linalg.norm(s, axis=1)
    rev = norm < 1e-9
    if rev.any():
        perp = np.cross(d[:-1][rev], [0.0, 0.0, 1.0])
        bad = np.linalg.norm(perp, axis=1) < 1e-9
        perp[bad] = np.cross(d[:-1][rev][bad], [1.0, 0.0, 0.0])
        s[rev] = perp
        norm[rev] = np.linalg.norm(perp, axis=1)
    m[1:-1] = s / norm[:, None]
    return m


def _hermite(
    p0: np.ndarray, p1: np.ndarray, m0: np.ndarray, m1: np.ndarray, u: np.ndarray
) -> np.ndarray:
    """Cubic Hermite segments (rows) evaluated at parameters ``u`` in [0, 1]."""
    u2, u3 = u * u, u * u * u
    return (
        (2 * u3 - 3 * u2 + 1)[:, None] * p0
        + (u3 - 2 * u2 + u)[:, None] * m0
        + (-2 * u3 + 3 * u2)[:, None] * p1
        + (u3 - u2)[:, None] * m1
    )


def _hermite_d(
    p0: np.ndarray, p1: np.ndarray, m0: np.ndarray, m1: np.ndarray, u: np.ndarray
) -> np.ndarray:
    """Derivative of :func:`_hermite` with respect to ``u``."""
    u2 = u * u
    return (
        (6 * u2 - 6 * u)[:, None] * p0
        + (3 * u2 - 4 * u + 1)[:, None] * m0
        + (-6 * u2 + 6 * u)[:, None] * p1
        + (3 * u2 - 2 * u)[:, None] * m1
    )


def _fillet_factor(theta: np.ndarray) -> np.ndarray:
    """Distance of a corner fillet's midpoint from the polyline, per unit setback ``c``."""
    return np.sin(theta) * (0.5 - 0.25 * np.cos(theta / 2))


def _fillet_corners(
    points: np.ndarray, extrude: np.ndarray, tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Replace every sharp corner by two waypoints set back along its legs.

    A corner turning by ``FILLET_MIN_DEG`` to ``FILLET_MAX_DEG`` at vertex V is
    replaced by A = V - c d_in and B = V + c d_out with tangents d_in and d_out:
    the Hermite segment A-B turns monotonically and stays within
    ``c * sin(t) * (0.5 - 0.25 cos(t / 2)) <= tol`` of the corner's legs.

    Returns
    -------
    points, tangents, extrude, corner
        Waypoints, unit tangents, per-segment extruder flags, and per segment the
        replaced corner vertex (NaN for segments that follow the polyline).
    """
    n = len(points)
    tangents = polyline_tangents(points)
    d = np.diff(points, axis=0)
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    sharp = np.zeros(n, dtype=bool)
    c = np.zeros(n)
    if n > 2:
        theta = np.arccos(np.clip(np.sum(u[:-1] * u[1:], axis=1), -1.0, 1.0))
        inner = (theta > np.radians(FILLET_MIN_DEG)) & (theta < np.radians(FILLET_MAX_DEG))
        sharp[1:-1] = inner
        setback = 0.9 * tol / np.maximum(_fillet_factor(theta), 1e-12)
        c[1:-1] = np.minimum(setback, 0.45 * np.minimum(length[:-1], length[1:]))
    counts = 1 + sharp
    vid = np.repeat(np.arange(n), counts)
    first = np.cumsum(counts) - counts
    is_a = np.zeros(len(vid), dtype=bool)
    is_a[first[sharp]] = True
    is_b = np.zeros(len(vid), dtype=bool)
    is_b[first[sharp] + 1] = True
    out = points[vid].copy()
    tan = tangents[vid].copy()
    ka, kb = np.flatnonzero(is_a), np.flatnonzero(is_b)
    out[ka] -= c[vid[ka], None] * u[vid[ka] - 1]
    out[kb] += c[vid[kb], None] * u[vid[kb]]
    tan[ka], tan[kb] = u[vid[ka] - 1], u[vid[kb]]
    seg_v = vid[:-1]
    ext = np.where(
        is_a[:-1],
        extrude[np.maximum(seg_v - 1, 0)] & extrude[np.minimum(seg_v, n - 2)],
        extrude[np.minimum(seg_v, n - 2)],
    )
    corner = np.full((len(out) - 1, 3), np.nan)
    corner[is_a[:-1]] = points[seg_v[is_a[:-1]]]
    return out, tan, ext, corner


def refine_waypoints(
    points: np.ndarray, extrude: np.ndarray, tol: float = 2.5e-4
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fillet sharp corners and add waypoints next to bends so the curve stays within ``tol``.

    Returns
    -------
    points, tangents, extrude, corner
        The refined waypoints (N', 3), their unit tangents, the per-segment
        extruder flags and, per segment, the polyline corner a fillet segment
        replaces (NaN elsewhere).
    """
    keep = np.concatenate(([True], np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-9))
    points = np.asarray(points, dtype=float)[keep]
    extrude = np.asarray(extrude, dtype=bool)[keep[1:]]
    points, tangents, extrude, corner = _fillet_corners(points, extrude, tol)
    for _ in range(60):
        d = np.diff(points, axis=0)
        length = np.linalg.norm(d, axis=1)
        u = d / length[:, None]
        s0 = np.sqrt(np.clip(1 - np.sum(tangents[:-1] * u, axis=1) ** 2, 0, 1))
        s1 = np.sqrt(np.clip(1 - np.sum(tangents[1:] * u, axis=1) ** 2, 0, 1))
        bad = (_BOUND * length * (s0 + s1) > tol) & np.isnan(corner[:, 0])
        if not bad.any():
            return points, tangents, extrude, corner
        # distance from each end at which the chord-aligned new waypoint goes
        c0 = np.where(s0 > 0, 0.9 * tol / (_BOUND * np.maximum(s0, 1e-300)), np.inf)
        c1 = np.where(s1 > 0, 0.9 * tol / (_BOUND * np.maximum(s1, 1e-300)), np.inf)
        c0 = np.minimum(c0, length / 3)
        c1 = np.minimum(c1, length / 3)
        idx = np.flatnonzero(bad)
        add0 = idx[np.isfinite(c0[idx]) & (s0[idx] > 0)]
        add1 = idx[np.isfinite(c1[idx]) & (s1[idx] > 0)]
        new_pos = np.concatenate([add0 + 1, add1 + 1])
        new_pts = np.concatenate(
            [
                points[add0] + u[add0] * c0[add0, None],
                points[add1 + 1] - u[add1] * c1[add1, None],
            ]
        )
        new_tan = np.concatenate([u[add0], u[add1]])
        new_ext = np.concatenate([extrude[add0], extrude[add1]])
        # keep the start-side insert before the end-side insert on the same segment
        order = np.lexsort((np.concatenate([np.zeros(len(add0)), np.ones(len(add1))]), new_pos))
        points = np.insert(points, new_pos[order], new_pts[order], axis=0)
        tangents = np.insert(tangents, new_pos[order], new_tan[order], axis=0)
        extrude = np.insert(extrude, new_pos[order] - 1, new_ext[order])
        corner = np.insert(corner, new_pos[order] - 1, np.nan, axis=0)
    raise RuntimeError("waypoint refinement did not converge")


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise distance of points ``p`` from segments ``a``-``b``."""
    ab = b - a
    w = np.clip(np.sum((p - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-300), 0, 1)
    return np.linalg.norm(p - (a + w[:, None] * ab), axis=1)


def sample_hermite(
    points: np.ndarray,
    speed: float,
    rate_hz: float = 100.0,
    extrude: np.ndarray | None = None,
    tol: float = 2.5e-4,
) -> SampledPath:
    """Sample the Hermite path through ``points`` at ``rate_hz`` at constant ``speed``.

    Parameters
    ----------
    points
        (N, 3) waypoints (metres), N >= 2.
    speed
        Tool speed along the path (m/s).
    rate_hz
        Sampling rate (Hz).
    extrude
        (N - 1,) extruder flag per segment; all on when omitted.
    tol
        Allowed distance of the curve from the polyline (metres).

    Returns
    -------
    SampledPath
        Samples ``speed / rate_hz`` apart along the curve.
    """
    points = np.asarray(points, dtype=float)
    if len(points) < 2:
        raise ValueError("a path needs at least two waypoints")
    if extrude is None:
        extrude = np.ones(len(points) - 1, dtype=bool)
    P, M, ext, corner = refine_waypoints(points, extrude, tol)
    chord = np.linalg.norm(np.diff(P, axis=0), axis=1)
    m0, m1 = M[:-1] * chord[:, None], M[1:] * chord[:, None]
    n_seg = len(chord)
    # arc length table: each segment cut into _TABLE pieces in u, each integrated by
    # Gauss-Legendre quadrature; u(s) is then interpolated in the table.
    u_knots = np.linspace(0.0, 1.0, _TABLE + 1)
    uq = (u_knots[:-1, None] + (0.5 * (_GL_NODES + 1))[None, :] / _TABLE).ravel()
    seg_rep = np.repeat(np.arange(n_seg), len(uq))
    u_rep = np.tile(uq, n_seg)
    sp = np.linalg.norm(
        _hermite_d(P[:-1][seg_rep], P[1:][seg_rep], m0[seg_rep], m1[seg_rep], u_rep), axis=1
    ).reshape(n_seg, _TABLE, len(_GL_NODES))
    piece_len = 0.5 / _TABLE * (sp @ _GL_WEIGHTS)
    s_table = np.concatenate(([0.0], np.cumsum(piece_len.ravel())))
    g_table = np.concatenate(([0.0], (np.arange(n_seg * _TABLE) + 1) / _TABLE))
    total = float(s_table[-1])
    step = speed / rate_hz
    n = int(np.floor(total / step + 1e-9))
    s = np.arange(n + 1) * step
    if total - n * step > 1e-9:
        s = np.append(s, total)
    g = np.interp(s, s_table, g_table)
    seg = np.clip(np.floor(g).astype(int), 0, n_seg - 1)
    u = np.clip(g - seg, 0.0, 1.0)
    args = (P[:-1][seg], P[1:][seg], m0[seg], m1[seg])
    pts = _hermite(*args, u)
    tan = _hermite_d(*args, u)
    tan /= np.maximum(np.linalg.norm(tan, axis=1), 1e-12)[:, None]
    # distance of each sample from its own chord, or for a fillet from the corner's two
    # legs: an upper bound of the distance to the polyline
    a, b = P[:-1][seg], P[1:][seg]
    dev = _point_segment_distance(pts, a, b)
    fil = np.flatnonzero(~np.isnan(corner[seg, 0]))
    if len(fil):
        v = corner[seg[fil]]
        dev[fil] = np.minimum(
            _point_segment_distance(pts[fil], a[fil], v),
            _point_segment_distance(pts[fil], v, b[fil]),
        )
    return SampledPath(
        t=np.arange(len(s)) / rate_hz,
        points=pts,
        tangents=tan,
        extrude=ext[seg],
        max_deviation=float(dev.max()),
        length=total,
    )


def order_contours(
    contours: list[np.ndarray], closed: list[bool], start: np.ndarray | None = None
) -> LayerPath:
    """Join contours into one layer path, nearest contour next, with travel moves between.

    A closed contour starts (its seam) at the vertex nearest to where the tool
    is; an open contour is reversed when its far end is nearer.

    Parameters
    ----------
    contours
        (N_i, 3) vertex arrays; closed ones repeat the first vertex at the end.
    closed
        Whether each contour is closed.
    start
        Where the tool starts (metres); the origin when omitted.
    """
    pos = np.zeros(3) if start is None else np.asarray(start, dtype=float)
    remaining = list(range(len(contours)))
    pts: list[np.ndarray] = []
    ext: list[np.ndarray] = []
    while remaining:
        best, best_d, best_k, best_rev = -1, np.inf, 0, False
        for i in remaining:
            c = contours[i]
            if closed[i]:
                d = np.linalg.norm(c[:-1] - pos, axis=1)
                k = int(np.argmin(d))
                cand = (d[k], k, False)
            else:
                d0, d1 = np.linalg.norm(c[0] - pos), np.linalg.norm(c[-1] - pos)
                cand = (d0, 0, False) if d0 <= d1 else (d1, 0, True)
            if cand[0] < best_d:
                best, (best_d, best_k, best_rev) = i, cand
        c = contours[best]
        if closed[best]:
            c = np.vstack([np.roll(c[:-1], -best_k, axis=0), c[best_k : best_k + 1]])
        elif best_rev:
            c = c[::-1]
        if pts:
            ext.append(np.array([False]))
        pts.append(c)
        ext.append(np.ones(len(c) - 1, dtype=bool))
        pos = c[-1]
        remaining.remove(best)
    points = np.vstack(pts)
    extrude = np.concatenate(ext)
    # the travel move joins the last vertex of one contour to the first of the next
    return LayerPath(points=points, extrude=extrude)


def slice_mesh(
    mesh: trimesh.Trimesh, layer_height: float, n_layers: int | None = None
) -> list[tuple[float, list[np.ndarray]]]:
    """Slice a mesh into closed contours, one set per layer.

    Layer ``k`` is cut at ``z_min + (k + 0.5) * layer_height`` (the middle of the
    layer, where the printed bead's cross-section is taken).

    Returns
    -------
    list of (z, contours)
        The cut height (mesh frame, metres) and the closed contours there, each
        (N, 3) with the first vertex repeated at the end.
    """
    z0, z1 = mesh.bounds[:, 2]
    n = int(np.floor((z1 - z0) / layer_height + 1e-9))
    if n_layers is not None:
        n = min(n, n_layers)
    heights = (np.arange(n) + 0.5) * layer_height
    sections = mesh.section_multiplane(
        plane_origin=[0.0, 0.0, z0], plane_normal=[0.0, 0.0, 1.0], heights=heights
    )
    out = []
    for h, sec in zip(heights, sections, strict=True):
        contours = []
        if sec is not None:
            to_3d = sec.metadata["to_3D"]
            for d in sec.discrete:
                p3 = np.column_stack([d, np.zeros(len(d))]) @ to_3d[:3, :3].T + to_3d[:3, 3]
                p3 = _drop_collinear(p3)
                if len(p3) >= 4:
                    contours.append(p3)
        out.append((float(z0 + h), contours))
    return out


def _drop_collinear(closed_pts: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Remove vertices of a closed polyline that lie on the line through their neighbours."""
    ring = closed_pts[:-1]
    prev, nxt = np.roll(ring, 1, axis=0), np.roll(ring, -1, axis=0)
    cross = np.linalg.norm(np.cross(ring - prev, nxt - ring), axis=1)
    keep = cross > tol * np.linalg.norm(nxt - prev, axis=1)
    ring = ring[keep]
    return np.vstack([ring, ring[:1]])


def _load_mesh(path: Path, factor: float) -> trimesh.Trimesh:
    import trimesh  # heavy; only mesh sources need it

    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(f"cannot read mesh: {exc}", path) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("the file holds no triangle mesh", path)
    if not mesh.is_watertight:
        raise InputError("the mesh is not watertight (its slices would not be closed)", path)
    mesh.apply_scale(factor)
    return mesh


_MESH_UNITS = {"auto": 1.0, "m": 1.0, "cm": 0.01, "mm": 1e-3, "in": 0.0254, "ft": 0.3048}


def print_path_elements(
    spec: PrintPathSpec, id_start: int = 0, source_index: int = 0
) -> list[Element]:
    """One ``print_path`` element per printed layer.

    Parameters
    ----------
    spec
        The print path source (a DXF drawing or a mesh).
    id_start
        Number of the first element id (``"P000"`` for 0).
    source_index
        Index of the source in ``project.elements`` (recorded in the attributes).

    Returns
    -------
    list of Element
        Layer ``k``: element frame at the drawing origin raised to the top of the
        layer, ``(k + 1) * layer_height``; ``polyline`` the layer's waypoints in
        that frame; ``supports`` the layer below.
    """
    T_world_origin = spec.origin.matrix()
    common = {
        "layer_height": spec.layer_height,
        "bead_width": spec.bead_width,
        "speed": spec.speed,
        "sample_rate_hz": spec.sample_rate_hz,
        "source_index": source_index,
    }
    layers: list[tuple[float, LayerPath, bool]] = []
    if spec.dxf is not None:
        contours: list[Contour] = read_dxf_contours(
            spec.dxf, spec.layers, spec.units, require_closed=spec.closed
        )
        layer_path = order_contours([c.points for c in contours], [c.closed for c in contours])
        all_closed = all(c.closed for c in contours)
        for k in range(spec.n_layers):
            layers.append(((k + 1) * spec.layer_height, layer_path, all_closed))
        common["source"] = spec.dxf.name
        common["dxf_layers"] = sorted({c.layer for c in contours})
    else:
        assert spec.mesh is not None
        mesh = _load_mesh(spec.mesh, _MESH_UNITS[spec.units])
        n_layers = spec.n_layers if "n_layers" in spec.model_fields_set else None
        z0 = float(mesh.bounds[0, 2])
        for k, (z_cut, rings) in enumerate(slice_mesh(mesh, spec.layer_height, n_layers)):
            if not rings:
                raise InputError(f"the mesh has no cross-section at z = {z_cut:.4f} m", spec.mesh)
            flat = [np.column_stack([r[:, :2], np.zeros(len(r))]) for r in rings]
            layers.append(
                (z0 + (k + 1) * spec.layer_height, order_contours(flat, [True] * len(flat)), True)
            )
        common["source"] = spec.mesh.name
    elements = []
    for k, (z, path, all_closed) in enumerate(layers):
        T_origin_layer = np.eye(4)
        T_origin_layer[2, 3] = z
        elements.append(
            Element(
                id=f"P{id_start + k:03d}",
                type="print_path",
                T_world_element=T_world_origin @ T_origin_layer,
                layer=k,
                supports=() if k == 0 else (f"P{id_start + k - 1:03d}",),
                part=None,
                robot_built=True,
                polyline=path.points,
                attributes={
                    **common,
                    "closed": all_closed,
                    "extrude": path.extrude.tolist(),
                    "length": path.print_length,
                    "travel_length": path.travel_length,
                },
            )
        )
    return elements


def element_tool_frames(element: Element) -> np.ndarray:
    """Tool frames in the world at the waypoints of a print path element.

    Returns
    -------
    numpy.ndarray
        (N, 4, 4) ``T_world_tool``: z down, x along the path.
    """
    if element.polyline is None:
        raise ValueError(f"element {element.id} has no polyline")
    T_el = tool_frames(element.polyline, polyline_tangents(element.polyline))
    return element.T_world_element @ T_el


def sample_print_path(element: Element, tol: float = 2.5e-4) -> tuple[SampledPath, np.ndarray]:
    """Sample a print path element at its rate and speed.

    Returns
    -------
    sampled, T_world_tool
        The samples (in the element frame) and the (M, 4, 4) tool frames in the world.
    """
    if element.polyline is None:
        raise ValueError(f"element {element.id} has no polyline")
    attrs = element.attributes
    extrude = np.asarray(attrs.get("extrude", np.ones(len(element.polyline) - 1)), dtype=bool)
    sampled = sample_hermite(
        element.polyline,
        float(attrs.get("speed", 0.1)),
        float(attrs.get("sample_rate_hz", 100.0)),
        extrude,
        tol,
    )
    return sampled, element.T_world_element @ tool_frames(sampled.points, sampled.tangents)
