"""Constant-speed sampling of print paths by cubic Hermite interpolation (paper 000).

Waypoints get tangents (:func:`polyline_tangents`), corners are filleted or
kept (:func:`refine_waypoints`), and :func:`sample_hermite` samples the curve
at a constant path speed and rate (100 Hz in the paper) within a deviation
tolerance of the polyline. Metres and seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_BOUND = 4.0 / 27.0
FILLET_MIN_DEG = 15.0
"""Corners turning more than this are filleted (smaller bends: bisector tangents)."""
FILLET_MAX_DEG = 150.0
"""Corners turning more than this (near reversals) keep a waypoint at the vertex."""
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(4)
_TABLE = 16


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
