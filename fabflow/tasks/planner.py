"""Slice a project into per-station work packages.

:func:`plan_project` runs the whole planning chain on the elements of a project:

1. tool targets of every robot-built element (:mod:`fabflow.tasks.targets`);
2. the arm's reach model, shrunk by ``planning.reach_margin`` (:mod:`fabflow.robots.reach_model`);
3. collision-free candidate platform poses and which elements each reaches at
   which lift heights (:mod:`fabflow.tasks.stations`);
4. few stations with short travel (:mod:`fabflow.tasks.cover`);
5. the build order across stations and the lift height of every visit
   (:mod:`fabflow.tasks.order`), off the levels where a block's descent passes
   the wrist singularity or the arm swings widely to reach it, where another
   level or station reaches (:mod:`fabflow.tasks.awkward_lifts`);
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
from scipy import sparse

from fabflow.design.elements import Element
from fabflow.errors import InfeasibleError, InputError, UnsupportedError
from fabflow.project import Project
from fabflow.robots.catalog import get_robot
from fabflow.robots.geometry import shoulder_radius
from fabflow.robots.reach_model import ReachModel, reach_model
from fabflow.tasks.awkward_lifts import awkward_levels, prefer_regular
from fabflow.tasks.cover import CoverResult, select_stations
from fabflow.tasks.order import (
    Visit,
    dissolve_small_visits,
    find_support_cycle,
    lift_bands,
    plan_visits,
    schedule,
    support_indices,
    topological_order,
)
from fabflow.tasks.plan import Plan, Station, WorkPackage
from fabflow.tasks.reachability import (
    MAX_LISTED,
    explain_unreachable,
    list_ids,
    reach_matrix,
    thin_frames,
    with_approach_frames,
)
from fabflow.tasks.split import split_wide_paths
from fabflow.tasks.stations import Candidates, generate_candidates, lift_levels
from fabflow.tasks.targets import tool_frames
from fabflow.tasks.verify import unreachable_targets

SPLIT_FRACTION = 0.35
"""Print paths wider than this fraction of the arm's reach (bounding-box half-diagonal)
are split into pieces."""


def _check_ids(elements: Sequence[Element]) -> None:
    seen: set[str] = set()
    dup: list[str] = []
    for e in elements:
        if e.id in seen:
            dup.append(e.id)
        seen.add(e.id)
    if dup:
        raise InputError(f"element ids must be unique; repeated: {', '.join(sorted(set(dup)))}")


def _platform_check(project: Project) -> None:
    T_pb = project.robot.platform.T_platform_base.matrix()
    if abs(T_pb[2, 2]) < math.cos(math.radians(1.0)):
        raise UnsupportedError(
            "the planner needs the arm base z axis vertical on the platform "
            "(robot.platform.T_platform_base tilts it)"
        )


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
    _platform_check(project)
    if reach is None:
        T_flange_tool = project.robot.tool.T_flange_tool.matrix()
        reach = reach_model(project.robot.name, T_flange_tool).shrunk(planning.reach_margin)

    elements, pieces = split_wide_paths(elements, SPLIT_FRACTION * reach.r_max)
    piece_ids = {p for ids in pieces.values() for p in ids}
    split_elements = tuple(e for e in elements if e.id in piece_ids)
    idx_work = [i for i, e in enumerate(elements) if e.robot_built]
    work = [elements[i] for i in idx_work]
    n = len(work)
    notes = _split_notes(pieces)
    if n == 0:
        return Plan(
            work_packages=(),
            notes=("the project has no robot-built elements; nothing to plan",),
            summary={"stations": 0, "visits": 0, "elements": 0, "travel_m": 0.0},
        )
    ids = [e.id for e in work]
    src, dst = _support_graph(work, {e.id for e in elements})
    T_frames, owner, T_targets, tilted = _frames_to_reach(project, work)

    lifts = lift_levels(project.robot.platform.lift, planning.lift_step)
    cands = generate_candidates(
        project.site,
        project.robot.platform,
        elements,
        T_frames[:, :2, 3],
        reach.r_max,
        planning.candidate_spacing,
        planning.headings_deg,
        shoulder_radius(get_robot(project.robot.name)) + project.program.clearance,
    )
    t_cand = time.perf_counter()
    A, coverage_notes = reach_matrix(
        project, cands, len(elements), idx_work, T_frames, owner, tilted, reach, lifts,
        (src, dst), ids,
    )  # fmt: skip
    notes += coverage_notes
    reachable = np.diff(A.tocsc().indptr) > 0
    t_cov = time.perf_counter()
    if not reachable.all():
        raise explain_unreachable(
            project, elements, work, np.flatnonzero(~reachable), T_targets[:, :3, 3], cands,
            reach, lifts,
        )  # fmt: skip

    start = np.asarray(planning.start if planning.start is not None else project.site.extent_min)
    res = select_stations(
        A,
        np.ones(n, dtype=bool),
        cands.base_xy,
        cands.xy,
        cands.blocks.astype(np.int64),
        reach.r_max,
        start,
    )
    k = len(res.chosen)
    t_sel = time.perf_counter()
    if planning.max_stations is not None and k > planning.max_stations:
        raise InfeasibleError(
            f"the plan needs {k} stations but planning.max_stations is {planning.max_stations}; "
            f"at least {res.lower_bound} are needed because elements "
            f"{list_ids([ids[i] for i in res.witnesses])} share no station"
        )
    A_ch = _regular_reach(project, A[res.chosen].tocsr(), res.chosen, cands, lifts, work)
    t_awk = time.perf_counter()
    visits = _visits(A_ch, res.chosen, cands, work, idx_work, (src, dst), T_targets, ids)
    t_ord = time.perf_counter()
    packages, travel_total = _work_packages(visits, A_ch, res.chosen, cands, lifts, ids, T_targets)
    t_end = time.perf_counter()

    notes += _station_notes(res, len(cands), len(visits), reach, ids)
    per_station: dict[str, int] = {}
    for wp in packages:
        per_station[wp.station.id] = per_station.get(wp.station.id, 0) + len(wp.elements)
    summary: dict[str, Any] = {
        "stations": k,
        "station_lower_bound": res.lower_bound,
        "greedy_stations": res.greedy_count,
        "selection": res.method,
        "stations_optimal": res.optimal,
        "visits": len(visits),
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
            "awkward_lifts": round(t_awk - t_sel, 4),
            "order": round(t_ord - t_awk, 4),
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


def _split_notes(pieces: dict[str, list[str]]) -> list[str]:
    """A note on the print paths split into per-station pieces, if any."""
    if not pieces:
        return []
    counts = sorted({len(v) for v in pieces.values()})
    return [
        f"{len(pieces)} print path(s) are wider than one station reaches and were split "
        f"into {'/'.join(map(str, counts))} pieces each ({list_ids(sorted(pieces))}); work "
        "packages name the pieces (plan.split_elements)"
    ]


def _support_graph(work: Sequence[Element], known: set[str]) -> tuple[np.ndarray, np.ndarray]:
    """Support edges ``(src, dst)`` among the robot-built elements (dst rests on src).

    Raises
    ------
    InputError
        For supports naming unknown elements.
    InfeasibleError
        When the supports form a cycle.
    """
    ids = [e.id for e in work]
    src, dst, missing_sup = support_indices(ids, [e.supports for e in work], known)
    if missing_sup:
        raise InputError("unknown supports: " + "; ".join(missing_sup[:MAX_LISTED]))
    cycle = find_support_cycle(len(work), src, dst)
    if cycle:
        chain = " -> ".join(ids[i] for i in [*cycle, cycle[0]])
        raise InfeasibleError(f"the supports form a cycle, so no build order exists: {chain}")
    return src, dst


def _frames_to_reach(
    project: Project, work: Sequence[Element]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The tool frames the planner checks, their element, the targets, the tilted elements.

    Returns
    -------
    T_frames, owner
        Thinned tool frames plus each element's approach pose (world, metres) and the
        index of the element each belongs to.
    T_targets
        (n, 4, 4) the first tool frame of every element (its target).
    tilted
        Elements with a frame more than 5 deg from pointing down.
    """
    T_frames, owner = tool_frames(work)
    first = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    T_targets = T_frames[first]
    T_frames, owner = with_approach_frames(
        T_frames, owner, [e.type for e in work], project.program.approach
    )
    tilted = np.unique(owner[T_frames[:, 2, 2] > -math.cos(math.radians(5.0))])
    keep = thin_frames(T_frames[:, :3, 3], owner, max(project.planning.reach_margin, 0.01))
    return T_frames[keep], owner[keep], T_targets, tilted


def _regular_reach(
    project: Project,
    A_ch: sparse.csr_matrix,
    chosen: np.ndarray,
    cands: Candidates,
    lifts: np.ndarray,
    work: Sequence[Element],
) -> sparse.csr_matrix:
    """The chosen stations' reach without the lift levels at which a block is awkward to
    build (:mod:`fabflow.tasks.awkward_lifts`) where another level or station reaches it."""
    coo = A_ch.tocoo()
    T_wp = np.stack([cands.T_world_platform(int(c)) for c in chosen])
    singular, swinging = awkward_levels(project, T_wp, lifts, work, coo.row, coo.col, coo.data)
    return prefer_regular(A_ch, singular, swinging)


def _visits(
    A_ch: sparse.csr_matrix,
    chosen: np.ndarray,
    cands: Candidates,
    work: Sequence[Element],
    idx_work: Sequence[int],
    supports: tuple[np.ndarray, np.ndarray],
    T_targets: np.ndarray,
    ids: Sequence[str],
) -> list[Visit]:
    """The build order across the chosen stations: visits in execution order."""
    src, dst = supports
    n = len(work)
    k = len(chosen)
    A_csc = A_ch.tocsc()
    A_csc.sort_indices()
    reach_sets = [A_csc.indices[A_csc.indptr[e] : A_csc.indptr[e + 1]] for e in range(n)]
    layer = np.array([e.layer for e in work], dtype=np.int64)
    topo = topological_order(n, src, dst, layer)
    blocked_ch = cands.blocked(chosen)[:, idx_work].tocsr()
    blocked_by = [
        blocked_ch.indices[blocked_ch.indptr[s] : blocked_ch.indptr[s + 1]] for s in range(k)
    ]
    visit, visit_station = plan_visits(reach_sets, src, dst, topo, cands.xy[chosen])
    fixed = np.zeros(n, dtype=bool)
    for blk in blocked_by:
        fixed[blk] = True
    visit = dissolve_small_visits(visit, visit_station, reach_sets, src, dst, fixed)
    return schedule(visit, visit_station, layer, T_targets[:, :3, 3], src, dst, blocked_by, ids)


def _work_packages(
    visits: Sequence[Visit],
    A_ch: sparse.csr_matrix,
    chosen: np.ndarray,
    cands: Candidates,
    lifts: np.ndarray,
    ids: Sequence[str],
    T_targets: np.ndarray,
) -> tuple[list[WorkPackage], float]:
    """One work package per stay at one lift height, and the total travel (metres).

    Station ids follow the order of first visit; ``A_ch`` is the chosen stations'
    reach (lift level bit masks), the awkward levels already taken out.
    """
    first_visit: dict[int, int] = {}
    for v in visits:
        first_visit.setdefault(v.station, len(first_visit))
    A_ch_r = A_ch.tocsr()
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
    return packages, travel_total


def _station_notes(
    res: CoverResult, n_candidates: int, n_visits: int, reach: ReachModel, ids: Sequence[str]
) -> list[str]:
    """Notes on the number of stations, the return visits and the reach model."""
    k = len(res.chosen)
    witnesses = list_ids([ids[i] for i in res.witnesses])
    if res.optimal:
        notes = [
            f"{k} stations is the fewest possible over the {n_candidates} collision-free "
            f"candidates (integer program solved to optimality); e.g. elements {witnesses} "
            "pairwise share no station"
        ]
    else:
        notes = [
            f"{k} stations ({res.method}); at least {res.lower_bound} are needed because "
            f"elements {witnesses} pairwise share no station"
        ]
    if n_visits > k:
        notes.append(
            f"{n_visits - k} return visit(s): elements rest on elements built from "
            "another station, so the plan comes back for the layers above"
        )
    if reach.source != "ik":
        notes.append(
            "reach model: geometric approximation from the robot's DH table "
            "(no inverse-kinematics reach map for this robot)"
        )
    return notes


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
