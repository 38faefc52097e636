"""Build order across stations: supports first, few visits, short arm travel.

The platform follows a repeating sequence of the chosen stations (the tour
``0, 1, ..., k-1`` over and over, or back and forth). Every element goes to the
earliest visit of that sequence whose station reaches it and that is not
before the visits of everything it rests on (:func:`assign_passes`). A part
that spans stations is thus built in bands of layers: each station builds what
it can, and the platform comes back for the layers above when they rest on
work done from another station. The planner tries each sequence and keeps
the one with the fewest visits, then the shortest travel.

Inside a visit the elements are built like a topological sort: the lowest
ready layer first and, inside a layer, the nearest next target (short arm
travel). A station whose footprint covers robot-built elements must be
finished before those elements are built.
"""

from __future__ import annotations

import heapq
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fabflow.errors import InfeasibleError


@dataclass(frozen=True)
class Visit:
    """One stay of the platform at a station.

    Attributes
    ----------
    station
        Index into the chosen stations.
    elements
        Element indices in build order.
    """

    station: int
    elements: np.ndarray


def support_indices(
    ids: Sequence[str], supports: Sequence[Sequence[str]], known: set[str]
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Support edges among the scheduled elements.

    Parameters
    ----------
    ids
        Ids of the scheduled elements (index = position).
    supports
        For every scheduled element, the ids it rests on.
    known
        Ids of every element of the project (pre-built ones count as present).

    Returns
    -------
    src, dst
        Edge arrays: element ``dst`` rests on element ``src`` (scheduled indices).
    missing
        Messages for supports that name no element.
    """
    index = {e: i for i, e in enumerate(ids)}
    src: list[int] = []
    dst: list[int] = []
    missing: list[str] = []
    for i, sup in enumerate(supports):
        for s in sup:
            j = index.get(s)
            if j is not None:
                src.append(j)
                dst.append(i)
            elif s not in known:
                missing.append(f"{ids[i]} rests on '{s}', which is not an element of the project")
    return np.array(src, dtype=np.intp), np.array(dst, dtype=np.intp), missing


def find_support_cycle(n: int, src: np.ndarray, dst: np.ndarray) -> list[int]:
    """A cycle in the support graph (element indices), or ``[]`` when there is none."""
    order = np.argsort(src, kind="stable")
    starts = np.searchsorted(src[order], np.arange(n + 1))
    out = dst[order]
    state = np.zeros(n, dtype=np.int8)
    for root in range(n):
        if state[root]:
            continue
        stack = [(root, starts[root])]
        path = [root]
        state[root] = 1
        while stack:
            v, k = stack[-1]
            if k < starts[v + 1]:
                stack[-1] = (v, k + 1)
                w = int(out[k])
                if state[w] == 1:
                    return path[path.index(w) :]
                if state[w] == 0:
                    state[w] = 1
                    stack.append((w, starts[w]))
                    path.append(w)
            else:
                state[v] = 2
                stack.pop()
                path.pop()
    return []


def visit_patterns(k: int) -> dict[str, np.ndarray]:
    """Repeating station sequences the plan may follow (tour positions, one period).

    ``cyclic``: 0, 1, ..., k-1, 0, 1, ...; ``back_and_forth``: 0, ..., k-1, k-2, ..., 1, 0, ...
    """
    out = {"cyclic": np.arange(k)}
    if k > 2:
        out["back_and_forth"] = np.r_[np.arange(k), np.arange(k - 2, 0, -1)]
    return out


def assign_passes(
    reach_sets: list[np.ndarray],
    src: np.ndarray,
    dst: np.ndarray,
    topo: np.ndarray,
    pattern: np.ndarray,
) -> np.ndarray:
    """Place every element at the earliest visit of a repeating station sequence.

    The platform follows ``pattern`` over and over; visit ``p`` is at station
    ``pattern[p % len(pattern)]``. Each element goes to the earliest visit whose
    station reaches it and that is not before the visits of its supports. This
    is the least such assignment, so it needs the fewest passes of the pattern.

    Parameters
    ----------
    reach_sets
        For every element, the tour positions of the stations that reach it.
    src, dst
        Support edges (dst rests on src).
    topo
        A topological order of the elements.
    pattern
        One period of the station sequence (tour positions).

    Returns
    -------
    np.ndarray
        (n,) visit index of every element.
    """
    n = len(reach_sets)
    period = len(pattern)
    k = int(pattern.max()) + 1 if period else 0
    offsets = [np.flatnonzero(pattern == r).tolist() for r in range(k)]
    order = np.argsort(dst, kind="stable")
    starts = np.searchsorted(dst[order], np.arange(n + 1)).tolist()
    sup_of = src[order].tolist()
    sets = [r.tolist() for r in reach_sets]
    visit = [0] * n
    # Plain Python ints: the sets are tiny and numpy's per-call cost would dominate.
    for e in topo.tolist():
        need = 0
        for s in sup_of[starts[e] : starts[e + 1]]:
            if visit[s] > need:
                need = visit[s]
        base = need - need % period
        best = -1
        for r in sets[e]:
            for o in offsets[r]:
                p = base + o
                if p < need:
                    p += period
                if best < 0 or p < best:
                    best = p
        visit[e] = best
    return np.array(visit, dtype=np.int64)


def topological_order(n: int, src: np.ndarray, dst: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Kahn's order of an acyclic support graph, smallest ``key`` first among ready ones."""
    indeg = np.bincount(dst, minlength=n)
    order = np.argsort(src, kind="stable")
    starts = np.searchsorted(src[order], np.arange(n + 1))
    out = dst[order]
    heap = [(key[i], i) for i in np.flatnonzero(indeg == 0)]
    heapq.heapify(heap)
    res = []
    while heap:
        _, v = heapq.heappop(heap)
        res.append(v)
        for w in out[starts[v] : starts[v + 1]]:
            indeg[w] -= 1
            if indeg[w] == 0:
                heapq.heappush(heap, (key[w], int(w)))
    return np.array(res, dtype=np.intp)


def schedule(
    visit: np.ndarray,
    visit_station: np.ndarray,
    layer: np.ndarray,
    p_target: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    blocked_by: list[np.ndarray],
    ids: Sequence[str],
) -> list[Visit]:
    """Sequence the elements visit by visit.

    Parameters
    ----------
    visit
        (n,) planned visit index of every element (from :func:`assign_passes`).
    visit_station
        Station (tour position) of every visit index.
    layer
        (n,) layer index of every element.
    p_target
        (n, 3) tool target positions (metres), for short arm travel.
    src, dst
        Support edges (dst rests on src).
    blocked_by
        For every station, the element indices under its footprint (built only
        after that station is finished).
    ids
        Element ids (for error messages).

    Returns
    -------
    list of Visit
        Stays in execution order; consecutive planned visits at the same station
        are merged.

    Raises
    ------
    InfeasibleError
        When no order satisfies the supports together with the footprint constraints.
    """
    n = len(visit)
    station = visit_station[visit]
    k = int(visit_station.max()) + 1 if len(visit_station) else 0
    indeg = np.bincount(dst, minlength=n).astype(np.int64)
    for blk in blocked_by:
        indeg[blk] += 1
    order = np.argsort(src, kind="stable")
    starts = np.searchsorted(src[order], np.arange(n + 1))
    out = dst[order]
    remaining = np.bincount(station, minlength=k)
    ready: dict[int, list[tuple[int, int]]] = {}
    groups: list[int] = []

    def push(e: int) -> None:
        g = int(visit[e])
        if g not in ready:
            ready[g] = []
            heapq.heappush(groups, g)
        heapq.heappush(ready[g], (int(layer[e]), e))

    for e in np.flatnonzero(indeg == 0):
        push(int(e))
    built = np.zeros(n, dtype=bool)
    stays: list[tuple[int, list[int]]] = []
    pos = p_target[0] if n else np.zeros(3)
    n_done = 0
    while n_done < n:
        while groups and not ready.get(groups[0]):
            ready.pop(heapq.heappop(groups), None)
        if not groups:
            _raise_stuck(built, station, src, dst, blocked_by, ids)
        g = groups[0]
        st = int(visit_station[g])
        if not stays or stays[-1][0] != st:
            stays.append((st, []))
        seq = stays[-1][1]
        q = ready[g]
        lay = q[0][0]
        batch = []
        while q and q[0][0] == lay:
            batch.append(heapq.heappop(q)[1])
        for e in _nearest_order(np.array(batch), p_target, pos):
            seq.append(int(e))
            built[e] = True
            n_done += 1
            pos = p_target[e]
            for w in out[starts[e] : starts[e + 1]]:
                indeg[w] -= 1
                if indeg[w] == 0:
                    push(int(w))
            remaining[station[e]] -= 1
            if remaining[station[e]] == 0:
                for w in blocked_by[station[e]]:
                    indeg[w] -= 1
                    if indeg[w] == 0:
                        push(int(w))
    return [
        Visit(station=s, elements=_layer_major(np.array(seq, dtype=np.intp), layer, src, dst))
        for s, seq in stays
    ]


def _layer_major(
    seq: np.ndarray, layer: np.ndarray, src: np.ndarray, dst: np.ndarray
) -> np.ndarray:
    """``seq`` stably sorted by layer, when that keeps every support before what rests on it.

    Planned visits at one station merge into one stay, each visit's elements
    after the other's: a station printing two pieces of a wall would print one
    to full height, then reach past it for the other's lower layers. Layer by
    layer the arm stays above what is built. Supports within one layer keep the
    order as it was.
    """
    order = seq[np.argsort(layer[seq], kind="stable")]
    position = np.full(len(layer), -1, dtype=np.int64)
    position[order] = np.arange(len(order))
    inside = (position[src] >= 0) & (position[dst] >= 0)
    if np.any(position[src[inside]] > position[dst[inside]]):
        return seq
    return order


def _nearest_order(batch: np.ndarray, p: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Greedy nearest-neighbour order of ``batch`` starting near ``start``."""
    m = len(batch)
    if m <= 1:
        return batch
    pts = p[batch]
    D = np.sum((pts[:, None, :] - pts[None, :, :]) ** 2, axis=2)
    d0 = np.sum((pts - start) ** 2, axis=1)
    out = np.empty(m, dtype=np.intp)
    j = int(np.argmin(d0))
    for i in range(m):
        out[i] = batch[j]
        D[:, j] = np.inf
        if i + 1 < m:
            j = int(np.argmin(D[j]))
    return out


def _raise_stuck(
    built: np.ndarray,
    station: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    blocked_by: list[np.ndarray],
    ids: Sequence[str],
) -> None:
    stuck = np.flatnonzero(~built)
    blocked_elem = {int(e): s for s, blk in enumerate(blocked_by) for e in blk}
    reasons = []
    for e in stuck[:10]:
        sups = src[(dst == e) & ~built[src]]
        parts = []
        if len(sups):
            parts.append("rests on " + ", ".join(ids[s] for s in sups[:3]) + " (not yet built)")
        if int(e) in blocked_elem:
            parts.append(f"lies under the footprint of station S{blocked_elem[int(e)] + 1}")
        reasons.append(f"{ids[e]}: " + "; ".join(parts or ["waits on another element"]))
    more = f" (and {len(stuck) - 10} more)" if len(stuck) > 10 else ""
    raise InfeasibleError(
        "no build order satisfies the supports: a station's footprint covers elements that "
        "other elements of that station rest on. Unbuildable: " + "; ".join(reasons) + more
    )


def lift_bands(masks: np.ndarray) -> np.ndarray:
    """Choose one lift level per element of a visit with as few changes as possible.

    Parameters
    ----------
    masks
        (m,) int bit masks of the lift levels reaching each element, in build order
        (every mask nonzero).

    Returns
    -------
    np.ndarray
        (m,) chosen lift level index per element. Greedy: keep the current level
        while it reaches; else switch to the level that reaches the longest run ahead.
    """
    m = len(masks)
    out = np.empty(m, dtype=np.intp)
    n_levels = int(masks.max()).bit_length() if m else 0
    bits = ((masks[:, None] >> np.arange(n_levels)[None, :]) & 1).astype(bool)
    # run[i, l]: how many consecutive elements from i on level l reaches.
    run = np.zeros((m + 1, n_levels), dtype=np.int64)
    for i in range(m - 1, -1, -1):
        run[i] = np.where(bits[i], run[i + 1] + 1, 0)
    cur = -1
    for i in range(m):
        if cur < 0 or not bits[i, cur]:
            cur = int(np.argmax(run[i]))
        out[i] = cur
    return out


def plan_visits(
    reach_sets: list[np.ndarray],
    src: np.ndarray,
    dst: np.ndarray,
    topo: np.ndarray,
    station_xy: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Planned visit of every element, part by part.

    Elements connected by supports form a part (a cabin, a printed wall); parts
    are planned one after the other, in the order of the first tour station
    that reaches them, so the platform finishes one part before it moves on.
    For each part, every sequence of :func:`visit_patterns` over the stations
    reaching it, in both directions, is tried with :func:`assign_passes`; the
    one with the fewest visits, then the shortest travel (counted from where
    the previous part ended), is kept.

    Parameters
    ----------
    reach_sets
        For every element, the sorted tour positions of the stations reaching it.
    src, dst
        Support edges (dst rests on src).
    topo
        A topological order of the elements.
    station_xy
        (k, 2) station positions in tour order (metres).

    Returns
    -------
    visit
        (n,) global visit index of every element.
    visit_station
        Station (tour position) of every visit index.
    """
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components

    n = len(reach_sets)
    graph = sparse.csr_matrix((np.ones(len(src)), (src, dst)), shape=(n, n))
    n_parts, part = connected_components(graph, directed=False)
    first = np.array([r[0] for r in reach_sets])
    part_first = np.full(n_parts, np.iinfo(np.int64).max)
    np.minimum.at(part_first, part, first)
    members = np.argsort(part, kind="stable")
    bounds = np.searchsorted(part[members], np.arange(n_parts + 1))
    rank = np.empty(n, dtype=np.intp)
    rank[topo] = np.arange(n)
    local_index = np.empty(n, dtype=np.intp)
    edge_part = part[src] if len(src) else np.zeros(0, dtype=np.intp)
    edge_order = np.argsort(edge_part, kind="stable")
    edge_bounds = np.searchsorted(edge_part[edge_order], np.arange(n_parts + 1))

    visit = np.zeros(n, dtype=np.int64)
    visit_station: list[int] = []
    here: int | None = None
    for p in np.argsort(part_first, kind="stable"):
        els = members[bounds[p] : bounds[p + 1]]
        local_index[els] = np.arange(len(els))
        stations = np.unique(np.concatenate([reach_sets[e] for e in els]))
        local_reach = [np.searchsorted(stations, reach_sets[e]) for e in els]
        edges = edge_order[edge_bounds[p] : edge_bounds[p + 1]]
        lsrc, ldst = local_index[src[edges]], local_index[dst[edges]]
        ltopo = local_index[els[np.argsort(rank[els], kind="stable")]]
        kk = len(stations)
        best: tuple[tuple[int, float], np.ndarray, np.ndarray] | None = None
        for perm in (np.arange(kk), np.arange(kk)[::-1]):
            for period in visit_patterns(kk).values():
                pattern = perm[period]
                lv = assign_passes(local_reach, lsrc, ldst, ltopo, pattern)
                used = np.unique(lv)
                seq = stations[pattern[used % len(pattern)]]
                seq = seq[np.r_[True, seq[1:] != seq[:-1]]]
                hops = seq if here is None else np.r_[here, seq]
                travel = float(np.hypot(*(station_xy[hops[1:]] - station_xy[hops[:-1]]).T).sum())
                key = (len(seq), travel)
                if best is None or key < best[0]:
                    best = (key, lv, stations[pattern[np.arange(int(lv.max()) + 1) % len(pattern)]])
            if kk == 1:
                break
        assert best is not None
        _, lv, lstations = best
        visit[els] = len(visit_station) + lv
        visit_station.extend(lstations.tolist())
        here = int(lstations[lv.max()])
    return visit, np.array(visit_station, dtype=np.intp)


SMALL_VISIT = 12
"""Visits with at most this many elements are candidates for :func:`dissolve_small_visits`."""


def dissolve_small_visits(
    visit: np.ndarray,
    visit_station: np.ndarray,
    reach_sets: list[np.ndarray],
    src: np.ndarray,
    dst: np.ndarray,
    fixed: np.ndarray,
) -> np.ndarray:
    """Move the elements of small visits into other planned visits where possible.

    An element may move to another planned visit whose station reaches it, that is
    not before the visits of what it rests on and not after the visits of what
    rests on it. A visit is dissolved only if all its elements can move; the
    smallest visits are tried first.

    Parameters
    ----------
    visit
        (n,) planned visit index of every element (from :func:`plan_visits`).
    visit_station
        Station of every visit index.
    reach_sets
        For every element, the tour positions of the stations reaching it.
    src, dst
        Support edges (dst rests on src).
    fixed
        (n,) bool: elements that must not move (e.g. under some station's footprint).

    Returns
    -------
    np.ndarray
        The new visit index of every element.
    """
    visit = visit.copy()
    n = len(visit)
    down_order = np.argsort(dst, kind="stable")
    down_starts = np.searchsorted(dst[down_order], np.arange(n + 1))
    sup_of = src[down_order]
    up_order = np.argsort(src, kind="stable")
    up_starts = np.searchsorted(src[up_order], np.arange(n + 1))
    dep_of = dst[up_order]
    counts = np.bincount(visit, minlength=len(visit_station))
    by_visit = np.argsort(visit, kind="stable")
    bounds = np.searchsorted(visit[by_visit], np.arange(len(visit_station) + 1))
    small = [int(v) for v in np.argsort(counts, kind="stable") if 0 < counts[v] <= SMALL_VISIT]
    for v in small:
        members = by_visit[bounds[v] : bounds[v + 1]]
        members = members[visit[members] == v]
        if len(members) == 0 or fixed[members].any():
            continue
        counts = np.bincount(visit, minlength=len(visit_station))
        # Planned (non-empty) visits of every station, ascending.
        at_station: dict[int, np.ndarray] = {}
        moved: dict[int, int] = {}
        order = members[
            np.argsort([len(sup_of[down_starts[e] : down_starts[e + 1]]) for e in members])
        ]
        ok = True
        for e in _topo_within(order, sup_of, down_starts):
            sups = sup_of[down_starts[e] : down_starts[e + 1]]
            deps = dep_of[up_starts[e] : up_starts[e + 1]]
            lo = max((moved.get(int(s), int(visit[s])) for s in sups), default=0)
            hi = min((int(visit[d]) for d in deps if visit[d] != v), default=10**18)
            best = -1
            for r in reach_sets[e]:
                r = int(r)
                if r not in at_station:
                    at_station[r] = np.flatnonzero((visit_station == r) & (counts > 0))
                cand = at_station[r]
                cand = cand[(cand >= lo) & (cand <= hi) & (cand != v)]
                if len(cand):
                    u = int(cand[np.argmin(np.abs(cand - v))])
                    if best < 0 or abs(u - v) < abs(best - v):
                        best = u
            if best < 0:
                ok = False
                break
            moved[int(e)] = best
        if ok:
            for e, u in moved.items():
                visit[e] = u
    return visit


def _topo_within(members: np.ndarray, sup_of: np.ndarray, starts: np.ndarray) -> list[int]:
    """Members ordered so that supports among them come first."""
    inside = set(members.tolist())
    done: set[int] = set()
    out: list[int] = []
    pending = list(members.tolist())
    while pending:
        rest = []
        for e in pending:
            if all(
                int(s) not in inside or int(s) in done for s in sup_of[starts[e] : starts[e + 1]]
            ):
                out.append(e)
                done.add(e)
            else:
                rest.append(e)
        if len(rest) == len(pending):
            out += rest
            break
        pending = rest
    return out
