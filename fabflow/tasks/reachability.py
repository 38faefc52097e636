"""Which candidate stations reach which elements, and why an element is reached by none.

The planner's coverage matrix holds, per candidate platform pose and element,
the bit mask of lift levels from which every tool frame of the element (and
its approach pose) is reachable (:func:`fabflow.tasks.stations.coverage`, by
the reach model). :func:`reach_matrix` adds what the reach table cannot judge:
tool frames that do not point down (by inverse kinematics) and candidates that
stand where robot-built elements go (usable only for what they do not block).
:func:`explain_unreachable` says, per element that no candidate reaches, why.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import shapely
from scipy import sparse
from scipy.spatial import cKDTree

from fabflow.design.elements import Element
from fabflow.errors import InfeasibleError
from fabflow.project import Project
from fabflow.robots.reach_model import ReachModel
from fabflow.tasks.stations import (
    Candidates,
    coverage,
    footprint_polygons,
    obstacle_polygons,
    unique_outlines,
)
from fabflow.tasks.targets import approach_poses, element_tool_frames
from fabflow.tasks.verify import ik_lift_masks

MAX_LISTED = 12
"""How many element ids an error message lists."""


def list_ids(ids: Sequence[str]) -> str:
    shown = ", ".join(ids[:MAX_LISTED])
    return shown + (f" (and {len(ids) - MAX_LISTED} more)" if len(ids) > MAX_LISTED else "")


def explain_unreachable(
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
    # One prepared outline per kind (stacked layers share one): testing the footprints
    # against it is fast however many elements stand on the same spot.
    robot_built = np.array([e.robot_built for e in elements], dtype=bool)
    outlines, outline_of = unique_outlines(elements)
    merged = {}
    kinds = {"pre-built elements": ~robot_built, "robot-built elements": robot_built}
    for kind, which in kinds.items():
        used = np.bincount(outline_of[which], minlength=len(outlines)) > 0
        if used.any():
            merged[kind] = shapely.union_all(outlines[used])
            shapely.prepare(merged[kind])
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
                    for kind, outline in merged.items():
                        if shapely.intersects(outline, fp).any():
                            causes.add(kind)
                why = (
                    f"at its height the arm reaches {r_ok:.1f} m at most, and every platform "
                    f"pose that close (footprint plus {platform.safety_margin:.2f} m margin) "
                    f"collides with {' or '.join(sorted(causes)) or 'something'}"
                )
        groups.setdefault(why, []).append(work[i].id)
    lines = [f"{list_ids(ids)}: {why}" for why, ids in groups.items()]
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
    """Tool frames plus each element's approach pose (as the programs approach it).

    See :func:`fabflow.tasks.targets.approach_poses`.

    Returns
    -------
    T_frames, owner
        The frames with one approach frame added per element, sorted by owner.
    """
    first = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    along_tool = np.array([types[i] == "task_point" for i in owner[first]])
    T_up = approach_poses(T_frames[first], along_tool, approach)
    T_all = np.concatenate([T_frames, T_up])
    owner_all = np.concatenate([owner, owner[first]])
    order = np.argsort(owner_all, kind="stable")
    return T_all[order], owner_all[order]


def reach_matrix(
    project: Project,
    cands: Candidates,
    n_elements: int,
    idx_work: Sequence[int],
    T_frames: np.ndarray,
    owner: np.ndarray,
    tilted: np.ndarray,
    reach: ReachModel,
    lifts: np.ndarray,
    supports: tuple[np.ndarray, np.ndarray],
    ids: Sequence[str],
) -> tuple[sparse.csr_matrix, list[str]]:
    """Coverage of the robot-built elements by the candidates, as lift bit masks.

    A candidate standing where robot-built elements go cannot build them nor
    anything resting on them; such candidates are used only when the others
    do not reach everything, and only near what the others miss.

    Parameters
    ----------
    project
        Robot, tool, platform mounting (for the inverse-kinematics check of tilted frames).
    cands
        Collision-free candidate platform poses.
    n_elements
        Number of all elements (robot-built and pre-built).
    idx_work
        Indices of the robot-built elements among all elements.
    T_frames, owner
        Tool frames to reach (world, metres) and the robot-built element of each.
    tilted
        Robot-built elements with a tool frame more than 5 deg from pointing down.
    reach
        The shrunk reach model; ``lifts`` the lift levels (metres).
    supports
        Support edges ``(src, dst)`` among the robot-built elements (dst rests on src).
    ids
        Element ids of the robot-built elements (for notes).

    Returns
    -------
    A, notes
        (candidates, robot-built elements) int64 lift masks, and notes for the plan.
    """
    notes: list[str] = []
    src, dst = supports
    n = len(idx_work)
    # Coverage columns run over all elements (pre-built columns stay empty: no frames).
    owner_all = np.asarray(idx_work, dtype=np.intp)[owner]
    n_blocked = cands.blocks.astype(np.int64)
    free_rows = np.flatnonzero(~cands.blocks)
    A = coverage(cands, T_frames, owner_all, n_elements, reach, lifts, free_rows)
    A = A[:, idx_work].tocsr()
    if len(tilted):
        A_tilted = _tilted_coverage(
            project, A, cands, free_rows, T_frames, owner, tilted, reach, lifts
        )
        if A_tilted is None:
            notes.append(
                f"{len(tilted)} element(s) have tool frames more than 5 deg from pointing "
                f"down ({list_ids([ids[i] for i in tilted])}); without closed-form inverse "
                "kinematics their reach was judged by position only"
            )
        else:
            A = A_tilted
    reachable = np.diff(A.tocsc().indptr) > 0
    if not reachable.all() and n_blocked.any():
        missing_xy = T_frames[np.isin(owner, np.flatnonzero(~reachable)), :2, 3]
        d, _ = cKDTree(missing_xy).query(cands.base_xy, distance_upper_bound=reach.r_max)
        extra = np.flatnonzero((n_blocked > 0) & np.isfinite(d))
        A_b = coverage(cands, T_frames, owner_all, n_elements, reach, lifts, extra)
        A_b = A_b[extra][:, idx_work].tocsr()
        above = _descendants(cands.blocked(extra)[:, idx_work].tocsr(), src, dst, n)
        A_b = (A_b - A_b.multiply(above)).tocsr()
        A_b.eliminate_zeros()
        A = (A + _embed_rows(A_b, extra, len(cands))).tocsr()
        if len(extra):
            notes.append(
                f"{len(extra)} candidate stations stand where robot-built elements go; they "
                "were considered because the others do not reach everything"
            )
    return A, notes
