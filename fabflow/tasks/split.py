"""Split print paths that no single station can print into per-station pieces.

A print path layer longer than the arm's reach cannot be printed from one
place. Such a layer is cut along its waypoints into consecutive pieces, each
small enough to fit in a circle of ``radius`` in plan view; neighbouring pieces
share their boundary waypoint, so together they print the whole path. A piece
is an ordinary ``print_path`` element with id ``"<parent>.<k>"`` (k from 1),
the parent's frame, the slice of its polyline and extrude flags, and the
attributes ``parent`` and ``waypoints`` (first and last waypoint index in the
parent).

Supports: when a piece's parent rests on a path split at the same waypoints
(stacked layers of an extruded wall), piece k rests on pieces k - 1, k and k + 1
of that path: its ends sit on the seams it shares with its neighbours' bead
below. So no station prints a layer of its stretch before the neighbouring
stretches have the layer below, and the plan alternates between the stations
layer by layer: a stretch printed ahead of its neighbour would stand in the
nozzle's way where the neighbour's next layer meets it at the seam. Otherwise a
piece rests on every piece of the parent's supports.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from fabflow.design.elements import Element


def cut_points(xy: np.ndarray, radius: float) -> list[tuple[int, int]]:
    """Consecutive waypoint ranges whose bounding boxes have half-diagonals <= ``radius``.

    Parameters
    ----------
    xy
        (N, 2) plan positions of the waypoints (metres), N >= 2.
    radius
        Largest allowed half-diagonal of a piece's bounding box (metres).

    Returns
    -------
    list of (first, last)
        Inclusive waypoint ranges; neighbours share their boundary waypoint.
    """
    n = len(xy)
    out: list[tuple[int, int]] = []
    a = 0
    while a < n - 1:
        lo = xy[a].copy()
        hi = xy[a].copy()
        b = a + 1
        while b < n:
            nlo, nhi = np.minimum(lo, xy[b]), np.maximum(hi, xy[b])
            if 0.5 * float(np.hypot(*(nhi - nlo))) > radius and b > a + 1:
                break
            lo, hi = nlo, nhi
            b += 1
        out.append((a, b - 1))
        a = b - 1
    return out


def split_wide_paths(
    elements: Sequence[Element], radius: float
) -> tuple[list[Element], dict[str, list[str]]]:
    """Replace every print path wider than ``radius`` by its pieces.

    Parameters
    ----------
    elements
        All elements; only robot-built print paths with a polyline are split.
    radius
        A piece must fit in a bounding box of this half-diagonal (metres).

    Returns
    -------
    elements
        The elements with wide paths replaced by their pieces (in place, in order).
    pieces
        Parent id -> piece ids, for the paths that were split.
    """
    ranges: dict[str, list[tuple[int, int]]] = {}
    for e in elements:
        if e.type != "print_path" or e.polyline is None or not e.robot_built:
            continue
        pts = np.asarray(e.polyline, dtype=float)
        if len(pts) < 3:
            continue
        xy = pts @ e.T_world_element[:3, :3].T[:, :2] + e.T_world_element[:2, 3]
        span = 0.5 * float(np.hypot(*(xy.max(axis=0) - xy.min(axis=0))))
        if span > radius:
            ranges[e.id] = cut_points(xy, radius)
    if not ranges:
        return list(elements), {}
    pieces: dict[str, list[str]] = {
        pid: [f"{pid}.{k + 1}" for k in range(len(r))] for pid, r in ranges.items()
    }
    out: list[Element] = []
    for e in elements:
        if e.id not in ranges:
            out.append(_remap_supports(e, pieces))
            continue
        same = [s for s in e.supports if s in ranges and ranges[s] == ranges[e.id]]
        for k, (a, b) in enumerate(ranges[e.id]):
            sup: list[str] = []
            for s in e.supports:
                if s in same:
                    # the piece and its neighbours below: they meet at the seams
                    sup += pieces[s][max(k - 1, 0) : k + 2]
                else:
                    sup.extend(pieces.get(s, [s]))
            attrs = dict(e.attributes)
            extrude = attrs.get("extrude")
            if isinstance(extrude, list) and len(extrude) == len(e.polyline) - 1:  # type: ignore[arg-type]
                attrs["extrude"] = extrude[a:b]
            poly = np.asarray(e.polyline)[a : b + 1]
            seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
            on = np.asarray(attrs.get("extrude", [True] * len(seg)), dtype=bool)
            attrs["length"] = float(seg[on].sum())
            attrs["travel_length"] = float(seg[~on].sum())
            attrs["parent"] = e.id
            attrs["waypoints"] = [a, b]
            out.append(
                dataclasses.replace(
                    e, id=pieces[e.id][k], polyline=poly, supports=tuple(sup), attributes=attrs
                )
            )
    return out, pieces


def _remap_supports(e: Element, pieces: dict[str, list[str]]) -> Element:
    if not any(s in pieces for s in e.supports):
        return e
    sup: list[str] = []
    for s in e.supports:
        sup.extend(pieces.get(s, [s]))
    return dataclasses.replace(e, supports=tuple(sup))


def with_pieces(elements: Sequence[Element], pieces: Sequence[Element]) -> list[Element]:
    """The elements with every split parent replaced by its pieces (and supports remapped)."""
    if not pieces:
        return list(elements)
    by_parent: dict[str, list[Element]] = {}
    for p in pieces:
        by_parent.setdefault(str(p.attributes["parent"]), []).append(p)
    ids = {pid: [p.id for p in ps] for pid, ps in by_parent.items()}
    out: list[Element] = []
    for e in elements:
        if e.id in by_parent:
            out.extend(by_parent[e.id])
        else:
            out.append(_remap_supports(e, ids))
    return out
