"""Slice a project into per-station work packages.

:func:`plan_project` runs the whole planning chain on the elements of a project:

1. tool targets of every robot-built element (:mod:`fabflow.tasks.targets`);
2. the arm's reach model, shrunk by ``planning.reach_margin`` (:mod:`fabflow.robots.reach_model`);
3. collision-free candidate platform poses and which elements each reaches at
   which lift heights (:mod:`fabflow.tasks.stations`);
4. few stations with short travel (:mod:`fabflow.tasks.cover`);
5. the build order across stations and the lift height of every visit
   (:mod:`fabflow.tasks.order`);
6. :class:`~fabflow.tasks.plan.WorkPackage` objects: one per stay of the
   platform at one lift height.

Station ids (``S1``, ``S2``, ...) follow the order of first visit. A station
visited at two lift heights gives two work packages with the same station id
and position and different ``lift``; the travel between them is 0.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import shapely
from scipy import sparse
from scipy.spatial import cKDTree

from fabflow.design.elements import Element
from fabflow.errors import InfeasibleError, InputError, UnsupportedError
from fabflow.project import Project
from fabflow.robots.reach_model import ReachModel, reach_model
from fabflow.tasks.cover import select_stations
from fabflow.tasks.order import (
    dissolve_small_visits,
    find_support_cycle,
    lift_bands,
    plan_visits,
    schedule,
    support_indices,
    topological_order,
)
from fabflow.tasks.plan import Plan, Station, WorkPackage
from fabflow.tasks.split import split_wide_paths
from fabflow.tasks.stations import (
    Candidates,
    coverage,
    element_polygons,
    footprint_polygons,
    generate_candidates,
    lift_levels,
    obstacle_polygons,
)
from fabflow.tasks.targets import element_tool_frames, tool_frames
from fabflow.tasks.verify import ik_lift_masks, unreachable_targets

SPLIT_FRACTION = 0.35
"""Print paths wider than this fraction of the arm's reach (bounding-box half-diagonal)
are split into pieces."""
MAX_LISTED = 12
"""How many element ids an error message lists."""


def _check_ids(elements: Sequence[Element]) -> None:
    seen: set[str] = set()
    dup: list[str] = []
    for e in elements:
        if e.id in seen:
            dup.append(e.id)
        seen.add(e.id)
    if dup:
        raise InputError(f"element ids must be unique; repeated: {', '.join(sorted(set(dup)))}")


def _list(ids: Sequence[str]) -> str:
    shown = ", ".join(ids[:MAX_LISTED])
    return shown + (f" (and {len(ids) - MAX_LISTED} more)" if len(ids) > MAX_LISTED else "")


def _platform_check(project: Project) -> None:
    T_pb = project.robot.platform.T_platform_base.matrix()
    if abs(T_pb[2, 2]) < math.cos(math.radians(1.0)):
        raise UnsupportedError(
            "the planner needs the arm base z axis vertical on the platform "
            "(robot.platform.T_platform_base tilts it)"
        )


def _explain_unreachable(
    project: Project,
    elements: Sequence[Element],
    work: Sequence[Element],
    missing: np.ndarray,
    p_target: np.ndarray,
    cands: Candidates,
    reach: ReachModel,
    lifts: np.ndarray,
) -> InfeasibleError:
    """Say for each unreachable element why no station reaches it."""
    site = project.site
    platform = project.robot.platform
    z_lo, z_hi = reach.z_range
    obstacles = obstacle_polygons(site)
    names = [ob.box.name if ob.box is not None else ob.polygon.name for ob in site.obstacles]  # type: ignore[union-attr]
    lo = np.asarray(site.extent_min)
    hi = np.asarray(site.extent_max)
    el_tree = shapely.STRtree(element_polygons(elements))
    robot_built = np.array([e.robot_built for e in elements], dtype=bool)
    groups: dict[str, list[str]] = {}
    for i in missing:
        p = p_target[i]
        z_rel = p[2] - cands.base_z0 - lifts
        frames = element_tool_frames(work[i])[:, :3, 3]
        span = float(shapely.minimum_bounding_radius(shapely.multipoints(frames[:, :2])))
        if span > reach.r_max:
            why = (
                f"its {len(frames)} tool frames spread over a circle of radius {span:.2f} m, "
                f"wider than the arm reaches from one station ({reach.r_max:.2f} m); "
                "split it into shorter elements"
            )
        elif z_rel.max() < z_lo or z_rel.min() > z_hi:
            why = (
                f"its target height {p[2]:.2f} m is outside what the arm reaches with the "
                f"lift ({cands.base_z0 + lifts[0] + z_lo:.2f} to "
                f"{cands.base_z0 + lifts[-1] + z_hi:.2f} m)"
            )
        elif (p[:2] < lo - reach.r_max).any() or (p[:2] > hi + reach.r_max).any():
            why = "it lies farther than the arm's reach outside the site extent"
        else:
            # Platform poses around the element that would reach it, ignoring collisions.
            ang = np.linspace(0, 2 * np.pi, 36, endpoint=False)
            rad = np.arange(0.5 * reach.r_step, reach.r_max, 0.05)
            A, Rr = np.meshgrid(ang, rad)
            ok_any = reach.reachable(Rr.ravel()[:, None], z_rel[None, :]).any(axis=1)
            if not ok_any.any():
                why = "no platform pose reaches it with the tool pointing down"
            else:
                r_ok = float(Rr.ravel()[ok_any].max())
                base = (
                    p[:2]
                    + np.stack([Rr.ravel() * np.cos(A.ravel()), Rr.ravel() * np.sin(A.ravel())], 1)[
                        ok_any
                    ]
                )
                causes: set[str] = set()
                off = platform.T_platform_base.matrix()[:2, 3]
                for h in np.radians(project.planning.headings_deg):
                    c, s = math.cos(h), math.sin(h)
                    xy = base - np.array([c * off[0] - s * off[1], s * off[0] + c * off[1]])
                    fp = footprint_polygons(
                        xy, np.full(len(xy), h), platform.footprint, platform.safety_margin
                    )
                    coords = shapely.get_coordinates(fp).reshape(len(fp), -1, 2)
                    if (~np.all((coords >= lo) & (coords <= hi), axis=(1, 2))).any():
                        causes.add("the site boundary")
                    for name, ob in zip(names, obstacles, strict=True):
                        if shapely.intersects(fp, ob).any():
                            causes.add(f"obstacle '{name}'")
                    hit = el_tree.query(fp, predicate="intersects")[1]
                    if (~robot_built[hit]).any():
                        causes.add("pre-built elements")
                    if robot_built[hit].any():
                        causes.add("robot-built elements")
                why = (
                    f"at its height the arm reaches {r_ok:.1f} m at most, and every platform "
                    f"pose that close (footprint plus {platform.safety_margin:.2f} m margin) "
                    f"collides with {' or '.join(sorted(causes)) or 'something'}"
                )
        groups.setdefault(why, []).append(work[i].id)
    lines = [f"{_list(ids)}: {why}" for why, ids in groups.items()]
    return InfeasibleError(
        f"{len(missing)} element(s) cannot be reached from any collision-free station:\n  "
        + "\n  ".join(lines)
    )


def _descendants(
    blocked: sparse.csr_matrix, src: np.ndarray, dst: np.ndarray, n: int
) -> sparse.csr_matrix:
    """Per candidate, its blocked elements and everything resting on them (transitively).

    Parameters
    ----------
    blocked
        (C, n) bool: elements under each candidate's footprint.
    src, dst
        Support edges (dst rests on src).
    n
        Number of elements.
    """
    up = sparse.csr_matrix((np.ones(len(src), dtype=np.int64), (src, dst)), shape=(n, n))
    reach = blocked.astype(np.int64).tocsr()
    frontier = reach
    while frontier.nnz:
        step = (frontier @ up).tocsr()
        step.data[:] = 1
        new = step - step.multiply(reach)
        new.eliminate_zeros()
        reach = (reach + new).tocsr()
        frontier = new
    reach.data[:] = 1
    return reach


def thin_frames(p: np.ndarray, owner: np.ndarray, step: float) -> np.ndarray:
    """Which tool frames to test for reach: about one per ``step`` metres of path.

    Every frame dropped lies within ``step`` (along the path) of a kept one of the
    same element, so with a reach model shrunk by at least ``step`` the dropped
    frames are inside the arm's unshrunk reach whenever the kept ones are. First
    and last frames stay.

    Parameters
    ----------
    p
        (K, 3) frame positions (metres), grouped by element.
    owner
        (K,) element index of every frame (non-decreasing).
    step
        Spacing along the path (metres).

    Returns
    -------
    np.ndarray
        (K,) bool mask of the frames to keep.
    """
    K = len(p)
    if K == 0:
        return np.zeros(0, dtype=bool)
    start = np.r_[True, owner[1:] != owner[:-1]]
    end = np.r_[owner[1:] != owner[:-1], True]
    seg = np.r_[0.0, np.linalg.norm(np.diff(p, axis=0), axis=1)]
    seg[start] = 0.0
    cum = np.cumsum(seg)
    cum -= np.maximum.accumulate(np.where(start, cum, 0.0))
    bucket = np.floor(cum / step).astype(np.int64)
    change = np.r_[True, bucket[1:] != bucket[:-1]]
    return start | end | change


def _tilted_coverage(
    project: Project,
    A: sparse.csr_matrix,
    cands: Candidates,
    rows: np.ndarray,
    T_frames: np.ndarray,
    owner: np.ndarray,
    tilted: np.ndarray,
    reach: ReachModel,
    lifts: np.ndarray,
) -> sparse.csr_matrix | None:
    """Redo the coverage of elements with tilted tool frames by inverse kinematics.

    Every frame of such an element must have an IK solution from the candidate at
    the same lift. Returns ``None`` when no closed-form IK is available.
    """
    sel = np.isin(owner, tilted)
    T_t, own_t = T_frames[sel], owner[sel]
    tree = cKDTree(cands.base_xy[rows])
    lists = tree.query_ball_point(T_t[:, :2, 3], reach.r_max + 0.5)
    f_idx = np.repeat(np.arange(len(T_t)), [len(x) for x in lists])
    c_idx = (
        rows[np.concatenate([np.asarray(x, dtype=np.intp) for x in lists])] if len(f_idx) else f_idx
    )
    T_wp = np.stack([cands.T_world_platform(int(c)) for c in c_idx]) if len(c_idx) else None
    masks = (
        ik_lift_masks(project, T_wp, T_t[f_idx], lifts)
        if T_wp is not None
        else np.zeros(0, dtype=np.int64)
    )
    if masks is None:
        return None
    e_idx = own_t[f_idx]
    # An element is reachable at a lift only if all its frames are.
    n_frames = np.bincount(own_t, minlength=A.shape[1])
    key = c_idx.astype(np.int64) * A.shape[1] + e_idx
    order = np.argsort(key, kind="stable")
    key, masks = key[order], masks[order]
    if len(key):
        first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        counts = np.diff(np.r_[first, len(key)])
        masks = np.bitwise_and.reduceat(masks, first)
        key = key[first]
    else:
        counts = np.zeros(0, dtype=np.int64)
    c_u, e_u = key // A.shape[1], key % A.shape[1]
    ok = (counts == n_frames[e_u]) & (masks != 0)
    new = sparse.csr_matrix((masks[ok], (c_u[ok], e_u[ok])), shape=A.shape, dtype=np.int64)
    keep_cols = np.ones(A.shape[1], dtype=np.int64)
    keep_cols[tilted] = 0
    return (A.multiply(keep_cols[None, :]) + new).tocsr()


def _embed_rows(M: sparse.csr_matrix, rows: np.ndarray, n_rows: int) -> sparse.csr_matrix:
    """Place the rows of ``M`` at ``rows`` of an otherwise empty (n_rows, ...) matrix."""
    coo = M.tocoo()
    return sparse.csr_matrix((coo.data, (rows[coo.row], coo.col)), shape=(n_rows, M.shape[1]))


def with_approach_frames(
    T_frames: np.ndarray, owner: np.ndarray, types: Sequence[str], approach: float
) -> tuple[np.ndarray, np.ndarray]:
    """Tool frames plus each element's approach pose, which the program also moves to.

    Blocks and print paths are approached from above (world z), task points back
    along the tool axis (as :mod:`fabflow.programs.motions` does), ``approach``
    metres away.

    Returns
    -------
    T_frames, owner
        The frames with one approach frame added per element, sorted by owner.
    """
    first = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    T_up = T_frames[first].copy()
    along_tool = np.array([types[i] == "task_point" for i in owner[first]])
    T_up[:, 2, 3] += np.where(along_tool, 0.0, approach)
    T_up[:, :3, 3] -= along_tool[:, None] * T_up[:, :3, 2] * approach
    T_all = np.concatenate([T_frames, T_up])
    owner_all = np.concatenate([owner, owner[first]])
    order = np.argsort(owner_all, kind="stable")
    return T_all[order], owner_all[order]


def plan_project(
    project: Project,
    elements: Sequence[Element],
    reach: ReachModel | None = None,
) -> Plan:
    """Plan stations, build order and work packages for a project.

    Parameters
    ----------
    project
        The validated project (site, robot, platform, planning settings).
    elements
        All elements of the design in the world frame; pre-built ones
        (``robot_built=False``) are obstacles that exist from the start.
    reach
        Reach model to use (default: :func:`~fabflow.robots.reach_model.reach_model` for
        the project's robot and tool, shrunk by ``planning.reach_margin``).

    Returns
    -------
    Plan
        Work packages in execution order, ``summary`` figures and ``notes``.

    Raises
    ------
    InfeasibleError
        When an element is not reachable from any collision-free station, the
        supports form a cycle or cannot be ordered with the station footprints,
        or the plan needs more than ``planning.max_stations`` stations. The
        message lists the element ids and why; nothing is planned.
    InputError
        For repeated element ids or supports naming unknown elements.
    """
    t0 = time.perf_counter()
    _check_ids(elements)
    planning = project.planning
    platform = project.robot.platform
    _platform_check(project)
    T_flange_tool = project.robot.tool.T_flange_tool.matrix()
    if reach is None:
        reach = reach_model(project.robot.model, T_flange_tool).shrunk(planning.reach_margin)

    elements, pieces = split_wide_paths(elements, SPLIT_FRACTION * reach.r_max)
    piece_ids = {p for ids in pieces.values() for p in ids}
    split_elements = tuple(e for e in elements if e.id in piece_ids)
    idx_work = [i for i, e in enumerate(elements) if e.robot_built]
    work = [elements[i] for i in idx_work]
    n = len(work)
    notes: list[str] = []
    if pieces:
        counts = sorted({len(v) for v in pieces.values()})
        notes.append(
            f"{len(pieces)} print path(s) are wider than one station reaches and were split "
            f"into {'/'.join(map(str, counts))} pieces each ({_list(sorted(pieces))}); work "
            "packages name the pieces (plan.split_elements)"
        )
    if n == 0:
        return Plan(
            work_packages=(),
            notes=("the project has no robot-built elements; nothing to plan",),
            summary={"stations": 0, "visits": 0, "elements": 0, "travel_m": 0.0},
        )

    known = {e.id for e in elements}
    ids = [e.id for e in work]
    src, dst, missing_sup = support_indices(ids, [e.supports for e in work], known)
    if missing_sup:
        raise InputError("unknown supports: " + "; ".join(missing_sup[:MAX_LISTED]))
    cycle = find_support_cycle(n, src, dst)
    if cycle:
        chain = " -> ".join(ids[i] for i in [*cycle, cycle[0]])
        raise InfeasibleError(f"the supports form a cycle, so no build order exists: {chain}")

    T_frames, owner = tool_frames(work)
    first = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    T_targets = T_frames[first]
    p_target = T_targets[:, :3, 3]
    T_frames, owner = with_approach_frames(
        T_frames, owner, [e.type for e in work], project.program.approach
    )
    tilted = np.unique(owner[T_frames[:, 2, 2] > -math.cos(math.radians(5.0))])
    keep = thin_frames(T_frames[:, :3, 3], owner, max(planning.reach_margin, 0.01))
    T_frames, owner = T_frames[keep], owner[keep]

    lifts = lift_levels(platform.lift, planning.lift_step)
    cands = generate_candidates(
        project.site,
        platform,
        elements,
        T_frames[:, :2, 3],
        reach.r_max,
        planning.candidate_spacing,
        planning.headings_deg,
    )
    t_cand = time.perf_counter()
    # Coverage columns run over all elements (pre-built columns stay empty: no frames).
    # A candidate standing where robot-built elements go cannot build them nor
    # anything resting on them; such candidates are used only when the others
    # do not reach everything, and only near what the others miss.
    owner_all = np.asarray(idx_work, dtype=np.intp)[owner]
    n_blocked = cands.blocks.astype(np.int64)
    free_rows = np.flatnonzero(~cands.blocks)
    A = coverage(cands, T_frames, owner_all, len(elements), reach, lifts, free_rows)
    A = A[:, idx_work].tocsr()
    if len(tilted):
        A = _tilted_coverage(project, A, cands, free_rows, T_frames, owner, tilted, reach, lifts)
        if A is None:
            notes.append(
                f"{len(tilted)} element(s) have tool frames more than 5 deg from pointing "
                f"down ({_list([ids[i] for i in tilted])}); without closed-form inverse "
                "kinematics their reach was judged by position only"
            )
            A = coverage(cands, T_frames, owner_all, len(elements), reach, lifts, free_rows)
            A = A[:, idx_work].tocsr()
    reachable = np.diff(A.tocsc().indptr) > 0
    if not reachable.all() and n_blocked.any():
        missing_xy = T_frames[np.isin(owner, np.flatnonzero(~reachable)), :2, 3]
        d, _ = cKDTree(missing_xy).query(cands.base_xy, distance_upper_bound=reach.r_max)
        extra = np.flatnonzero((n_blocked > 0) & np.isfinite(d))
        A_b = coverage(cands, T_frames, owner_all, len(elements), reach, lifts, extra)
        A_b = A_b[extra][:, idx_work].tocsr()
        above = _descendants(cands.blocked(extra)[:, idx_work].tocsr(), src, dst, n)
        A_b = (A_b - A_b.multiply(above)).tocsr()
        A_b.eliminate_zeros()
        A = (A + _embed_rows(A_b, extra, len(cands))).tocsr()
        reachable = np.diff(A.tocsc().indptr) > 0
        if len(extra):
            notes.append(
                f"{len(extra)} candidate stations stand where robot-built elements go; they "
                "were considered because the others do not reach everything"
            )
    t_cov = time.perf_counter()

    if not reachable.all():
        raise _explain_unreachable(
            project, elements, work, np.flatnonzero(~reachable), p_target, cands, reach, lifts
        )

    start = np.asarray(planning.start if planning.start is not None else project.site.extent_min)
    res = select_stations(
        A, np.ones(n, dtype=bool), cands.base_xy, cands.xy, n_blocked, reach.r_max, start
    )
    chosen = res.chosen
    k = len(chosen)
    t_sel = time.perf_counter()
    if planning.max_stations is not None and k > planning.max_stations:
        raise InfeasibleError(
            f"the plan needs {k} stations but planning.max_stations is {planning.max_stations}; "
            f"at least {res.lower_bound} are needed because elements "
            f"{_list([ids[i] for i in res.witnesses])} share no station"
        )

    A_ch = A[chosen].tocsc()
    A_ch.sort_indices()
    reach_sets = [A_ch.indices[A_ch.indptr[e] : A_ch.indptr[e + 1]] for e in range(n)]
    layer = np.array([e.layer for e in work], dtype=np.int64)
    topo = topological_order(n, src, dst, layer)
    blocked_ch = cands.blocked(chosen)[:, idx_work].tocsr()
    blocked_by = [
        blocked_ch.indices[blocked_ch.indptr[s] : blocked_ch.indptr[s + 1]] for s in range(k)
    ]
    station_xy = cands.xy[chosen]
    visit, visit_station = plan_visits(reach_sets, src, dst, topo, station_xy)
    fixed = np.zeros(n, dtype=bool)
    for blk in blocked_by:
        fixed[blk] = True
    visit = dissolve_small_visits(visit, visit_station, reach_sets, src, dst, fixed)
    visits = schedule(visit, visit_station, layer, p_target, src, dst, blocked_by, ids)
    t_ord = time.perf_counter()

    # Station ids in order of first visit.
    first_visit: dict[int, int] = {}
    for v in visits:
        first_visit.setdefault(v.station, len(first_visit))
    A_ch_r = A[chosen].tocsr()
    packages: list[WorkPackage] = []
    prev_xy: np.ndarray | None = None
    travel_total = 0.0
    for v in visits:
        c = int(chosen[v.station])
        masks = np.asarray(A_ch_r[v.station, v.elements].todense()).ravel().astype(np.int64)
        levels = lift_bands(masks)
        cuts = np.flatnonzero(np.diff(levels)) + 1
        T_wp = cands.T_world_platform(c)
        for seg in np.split(np.arange(len(v.elements)), cuts):
            els = v.elements[seg]
            station = Station(
                id=f"S{first_visit[v.station] + 1}",
                T_world_platform=T_wp,
                lift=float(lifts[levels[seg[0]]]),
            )
            travel = 0.0 if prev_xy is None else float(np.hypot(*(cands.xy[c] - prev_xy)))
            travel_total += travel
            prev_xy = cands.xy[c]
            packages.append(
                WorkPackage(
                    index=len(packages),
                    station=station,
                    elements=tuple(ids[i] for i in els),
                    T_world_targets=T_targets[els],
                    travel=travel,
                )
            )
    t_end = time.perf_counter()

    per_station: dict[str, int] = {}
    for wp in packages:
        per_station[wp.station.id] = per_station.get(wp.station.id, 0) + len(wp.elements)
    station_visits = len(visits)
    witnesses = _list([ids[i] for i in res.witnesses])
    if res.optimal:
        notes.append(
            f"{k} stations is the fewest possible over the {len(cands)} collision-free "
            f"candidates (integer program solved to optimality); e.g. elements {witnesses} "
            "pairwise share no station"
        )
    else:
        notes.append(
            f"{k} stations ({res.method}); at least {res.lower_bound} are needed because "
            f"elements {witnesses} pairwise share no station"
        )
    if station_visits > k:
        notes.append(
            f"{station_visits - k} return visit(s): elements rest on elements built from "
            "another station, so the plan comes back for the layers above"
        )
    if reach.source != "ik":
        notes.append(
            "reach model: geometric fallback from the robot's published dimensions "
            "(inverse kinematics of the robots module not available)"
        )
    summary: dict[str, Any] = {
        "stations": k,
        "station_lower_bound": res.lower_bound,
        "greedy_stations": res.greedy_count,
        "selection": res.method,
        "stations_optimal": res.optimal,
        "visits": station_visits,
        "work_packages": len(packages),
        "elements": n,
        "elements_per_station": per_station,
        "travel_m": round(travel_total, 3),
        "candidates": {"grid": cands.n_grid, "collision_free": len(cands)},
        "lift_levels_m": [round(float(x), 3) for x in lifts],
        "reach_model": reach.source,
        "reach_margin_m": planning.reach_margin,
        "time_s": {
            "candidates": round(t_cand - t0, 4),
            "coverage": round(t_cov - t_cand, 4),
            "selection": round(t_sel - t_cov, 4),
            "order": round(t_ord - t_sel, 4),
            "packages": round(t_end - t_ord, 4),
            "total": round(t_end - t0, 4),
        },
    }
    return Plan(
        work_packages=tuple(packages),
        notes=tuple(notes),
        summary=summary,
        split_elements=split_elements,
    )


def make_plan(project: Project, elements: Sequence[Element]) -> Plan:
    """Plan the project and record the inverse-kinematics check of every target."""
    plan = plan_project(project, elements)
    bad = unreachable_targets(plan, project)
    notes = plan.notes
    if bad:
        notes = (
            *notes,
            f"{len(bad)} target(s) fail the inverse-kinematics check: {', '.join(bad[:12])}",
        )
    return dataclasses.replace(plan, notes=notes, summary={**plan.summary, "ik_unreachable": bad})
