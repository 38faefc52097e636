"""Station selection: few stations that together reach every element, short travel.

Greedy set cover (lazy evaluation, ties to candidates that block nothing),
then local improvement:

1. drop stations whose elements the others already reach;
2. merge pairs: replace two nearby stations by one candidate that reaches
   every element only those two reached;
3. shorten travel: move each station to the candidate that still reaches its
   exclusive elements and sits closest to its neighbours on the tour.

When the instance is small enough (``ILP_MAX_NNZ``), the minimum set cover is
then solved exactly as an integer program (HiGHS through
:func:`scipy.optimize.milp`, with a time limit); its answer replaces the
greedy one when it uses fewer stations, and a solved program proves the count
minimal. Step 3 runs last in either case.

A lower bound on the station count comes from elements with no candidate in
common: they need distinct stations.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import Bounds, LinearConstraint, milp
from scipy.spatial import cKDTree

ILP_MAX_NNZ = 200_000
"""Largest coverage matrix (nonzeros) handed to the exact integer program."""
ILP_TIME_LIMIT_S = 3.0


@dataclass(frozen=True)
class CoverResult:
    """Chosen candidates and how good the choice is.

    Attributes
    ----------
    chosen
        Candidate indices in tour order.
    lower_bound
        Proven lower bound on the number of stations.
    witnesses
        Element indices that pairwise share no candidate (the proof of the bound).
    greedy_count
        Stations after the greedy pass (before local improvement).
    method
        ``"greedy"`` or ``"ilp"``: which step produced the station set.
    optimal
        The integer program proved the station count minimal.
    """

    chosen: np.ndarray
    lower_bound: int
    witnesses: np.ndarray
    greedy_count: int
    method: str
    optimal: bool


def _row(B: sparse.csr_matrix, c: int) -> np.ndarray:
    return B.indices[B.indptr[c] : B.indptr[c + 1]]


def greedy_cover(B: sparse.csr_matrix, required: np.ndarray, n_blocked: np.ndarray) -> list[int]:
    """Lazy greedy set cover.

    Parameters
    ----------
    B
        (C, N) bool CSR: candidate c reaches element e.
    required
        (N,) bool: elements that must be covered (all must be coverable).
    n_blocked
        (C,) number of elements each candidate blocks (ties prefer fewer).
    """
    uncovered = required.copy()
    gains = np.asarray(B[:, required].sum(axis=1)).ravel()
    heap = [
        (-int(g), int(nb), int(c))
        for c, (g, nb) in enumerate(zip(gains, n_blocked, strict=False))
        if g > 0
    ]
    heapq.heapify(heap)
    chosen: list[int] = []
    left = int(uncovered.sum())
    while left > 0 and heap:
        neg, nb, c = heapq.heappop(heap)
        gain = int(uncovered[_row(B, c)].sum())
        if gain == 0:
            continue
        if gain < -neg:
            heapq.heappush(heap, (-gain, nb, c))
            continue
        chosen.append(c)
        uncovered[_row(B, c)] = False
        left -= gain
    return chosen


def _counts(B: sparse.csr_matrix, chosen: list[int], n: int) -> np.ndarray:
    cnt = np.zeros(n, dtype=np.int64)
    for c in chosen:
        cnt[_row(B, c)] += 1
    return cnt


def _exclusive(B: sparse.csr_matrix, c: int, cnt: np.ndarray, required: np.ndarray) -> np.ndarray:
    row = _row(B, c)
    return row[(cnt[row] == 1) & required[row]]


def _covering(Bc: sparse.csc_matrix, cols: np.ndarray, n_cand: int) -> np.ndarray:
    """Candidates that reach every element in ``cols``."""
    if len(cols) == 0:
        return np.arange(n_cand)
    sub = Bc[:, cols]
    hits = np.bincount(sub.indices, minlength=n_cand)
    return np.flatnonzero(hits == len(cols))


def prune(B: sparse.csr_matrix, chosen: list[int], required: np.ndarray) -> list[int]:
    """Drop stations whose required elements are all reached by other stations."""
    chosen = list(chosen)
    cnt = _counts(B, chosen, B.shape[1])
    changed = True
    while changed:
        changed = False
        sizes = [len(_exclusive(B, c, cnt, required)) for c in chosen]
        for k in np.argsort(sizes, kind="stable"):
            if sizes[k] == 0:
                c = chosen.pop(int(k))
                cnt[_row(B, c)] -= 1
                changed = True
                break
    return chosen


def merge_pairs(
    B: sparse.csr_matrix,
    Bc: sparse.csc_matrix,
    chosen: list[int],
    required: np.ndarray,
    base_xy: np.ndarray,
    n_blocked: np.ndarray,
    r_max: float,
) -> list[int]:
    """Replace pairs of stations by one candidate where one suffices."""
    chosen = list(chosen)
    n_cand = B.shape[0]
    cnt = _counts(B, chosen, B.shape[1])
    tried: set[tuple[int, int]] = set()
    improved = True
    while improved and len(chosen) > 1:
        improved = False
        pos = base_xy[chosen]
        pairs = cKDTree(pos).query_pairs(2.0 * r_max + 1e-9, output_type="ndarray")
        for i, j in pairs:
            ci, cj = chosen[i], chosen[j]
            # A pair that could not merge is not tried again (keeps this linear in
            # the number of nearby pairs; merges elsewhere rarely change its answer).
            if (min(ci, cj), max(ci, cj)) in tried:
                continue
            tried.add((min(ci, cj), max(ci, cj)))
            both = np.union1d(_row(B, ci), _row(B, cj))
            cnt_ij = cnt[both] - np.isin(both, _row(B, ci)) - np.isin(both, _row(B, cj))
            need = both[(cnt_ij == 0) & required[both]]
            options = _covering(Bc, need, n_cand)
            if len(options) == 0:
                continue
            mid = 0.5 * (base_xy[ci] + base_xy[cj])
            score = n_blocked[options] * 1e6 + np.hypot(*(base_xy[options] - mid).T)
            best = int(options[np.argmin(score)])
            cnt[_row(B, ci)] -= 1
            cnt[_row(B, cj)] -= 1
            cnt[_row(B, best)] += 1
            chosen = [c for k, c in enumerate(chosen) if k not in (i, j)] + [best]
            improved = True
            break
    return chosen


def tour(xy: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """Short open path through points: nearest neighbour from ``start``, then 2-opt.

    Parameters
    ----------
    xy
        (k, 2) points (metres).
    start
        A point the path should begin near (the first stop is the closest point to it).

    Returns
    -------
    np.ndarray
        Permutation of ``range(k)``.
    """
    k = len(xy)
    if k <= 2:
        if k == 2 and start is not None:
            d = np.hypot(*(xy - start).T)
            return np.argsort(d)
        return np.arange(k)
    D = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    first = 0 if start is None else int(np.argmin(np.hypot(*(xy - start).T)))
    order = [first]
    free = np.ones(k, dtype=bool)
    free[first] = False
    for _ in range(k - 1):
        d = np.where(free, D[order[-1]], np.inf)
        nxt = int(np.argmin(d))
        order.append(nxt)
        free[nxt] = False
    path = np.array(order)
    improved = True
    while improved:
        improved = False
        for i in range(1, k - 1):
            a, b = path[i - 1], path[i]
            js = np.arange(i + 1, k)
            c = path[js]
            d_next = np.where(js + 1 < k, D[c, path[np.minimum(js + 1, k - 1)]], 0.0)
            e_next = np.where(js + 1 < k, D[b, path[np.minimum(js + 1, k - 1)]], 0.0)
            delta = D[a, c] + e_next - D[a, b] - d_next
            j = int(np.argmin(delta))
            if delta[j] < -1e-9:
                jj = int(js[j])
                path[i : jj + 1] = path[i : jj + 1][::-1].copy()
                improved = True
    return path


def shorten_travel(
    B: sparse.csr_matrix,
    Bc: sparse.csc_matrix,
    chosen: list[int],
    required: np.ndarray,
    base_xy: np.ndarray,
    xy: np.ndarray,
    n_blocked: np.ndarray,
    start: np.ndarray | None,
    rounds: int = 2,
) -> list[int]:
    """Move stations along their feasible region to shorten the tour between them."""
    chosen = list(chosen)
    if len(chosen) < 2:
        return chosen
    n_cand = B.shape[0]
    cnt = _counts(B, chosen, B.shape[1])
    for _ in range(rounds):
        order = tour(xy[chosen], start)
        chosen = [chosen[k] for k in order]
        moved = False
        for k, c in enumerate(chosen):
            need = _exclusive(B, c, cnt, required)
            options = _covering(Bc, need, n_cand)
            options = options[n_blocked[options] <= n_blocked[c]]
            nbrs = [chosen[m] for m in (k - 1, k + 1) if 0 <= m < len(chosen)]
            if not nbrs or len(options) == 0:
                continue
            cost = sum(np.hypot(*(xy[options] - xy[m]).T) for m in nbrs)
            here = sum(math.hypot(*(xy[c] - xy[m])) for m in nbrs)
            best = int(options[np.argmin(cost)])
            if cost.min() < here - 1e-6:
                cnt[_row(B, c)] -= 1
                cnt[_row(B, best)] += 1
                chosen[k] = best
                moved = True
        if not moved:
            break
    order = tour(xy[chosen], start)
    return [chosen[k] for k in order]


def exact_cover(
    B: sparse.csr_matrix, required: np.ndarray, n_blocked: np.ndarray, time_limit: float
) -> tuple[list[int], bool] | None:
    """Minimum set cover as an integer program.

    Returns
    -------
    tuple or None
        The chosen candidates and whether HiGHS proved them optimal, or ``None``
        when no solution was found within ``time_limit`` seconds.
    """
    C = B.shape[0]
    # Among covers of equal size prefer stations that reach more (overlapping
    # stations leave the build order room to finish parts in one pass) and that
    # block nothing. Both terms together stay below one station.
    size = np.diff(B.indptr).astype(float)
    cost = 1.0 + 1e-3 * (n_blocked > 0) - 0.5 * size / max(float(size.max()), 1.0) / max(C, 1)
    res = milp(
        cost,
        constraints=LinearConstraint(B[:, required].T.tocsr().astype(float), lb=1.0, ub=np.inf),
        integrality=np.ones(C),
        bounds=Bounds(0.0, 1.0),
        options={"time_limit": float(time_limit), "disp": False},
    )
    if res.x is None:
        return None
    chosen = [int(c) for c in np.flatnonzero(res.x > 0.5)]
    return chosen, bool(res.status == 0)


def lower_bound(Bc: sparse.csc_matrix, required: np.ndarray) -> np.ndarray:
    """Elements that pairwise share no candidate (greedy, hardest elements first).

    Their number is a lower bound on the number of stations.
    """
    n_cand = Bc.shape[0]
    used = np.zeros(n_cand, dtype=bool)
    degree = np.diff(Bc.indptr)
    picked = []
    for e in np.argsort(degree, kind="stable"):
        if not required[e] or degree[e] == 0:
            continue
        rows = Bc.indices[Bc.indptr[e] : Bc.indptr[e + 1]]
        if not used[rows].any():
            used[rows] = True
            picked.append(int(e))
    return np.array(picked, dtype=np.intp)


def select_stations(
    A: sparse.csr_matrix,
    required: np.ndarray,
    base_xy: np.ndarray,
    xy: np.ndarray,
    n_blocked: np.ndarray,
    r_max: float,
    start: np.ndarray | None = None,
) -> CoverResult:
    """Choose stations reaching every required element (see the module docstring).

    Parameters
    ----------
    A
        (C, N) coverage (nonzero = reachable at some lift).
    required
        (N,) bool: elements to cover; every one must have a candidate.
    base_xy, xy
        (C, 2) arm base and platform positions of the candidates (metres).
    n_blocked
        (C,) number of robot-built elements under each candidate's footprint.
    r_max
        Horizontal reach of the arm (metres).
    start
        Where the platform arrives on site; the tour starts near it.
    """
    B = (A != 0).tocsr()
    B.sort_indices()
    Bc = B.tocsc()
    Bc.sort_indices()
    chosen = greedy_cover(B, required, n_blocked)
    greedy_count = len(chosen)
    chosen = prune(B, chosen, required)
    chosen = merge_pairs(B, Bc, chosen, required, base_xy, n_blocked, r_max)
    chosen = prune(B, chosen, required)
    method, optimal = "greedy", False
    if B.nnz <= ILP_MAX_NNZ and len(chosen) > 1:
        exact = exact_cover(B, required, n_blocked, ILP_TIME_LIMIT_S)
        if exact is not None and len(exact[0]) <= len(chosen):
            chosen, optimal = exact
            method = "ilp"
    chosen = shorten_travel(B, Bc, chosen, required, base_xy, xy, n_blocked, start)
    wit = lower_bound(Bc, required)
    return CoverResult(
        chosen=np.array(chosen, dtype=np.intp),
        lower_bound=len(chosen) if optimal else len(wit),
        witnesses=wit,
        greedy_count=greedy_count,
        method=method,
        optimal=optimal,
    )
