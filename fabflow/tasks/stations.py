"""Candidate platform poses on the free site and what each of them can build.

A candidate is a platform pose (x, y, heading) on a regular grid over the site.
Its footprint grown by the safety margin (a plan-view rectangle) must stay
inside the site extent and clear of every site obstacle and every element that
is there before the robot starts (not robot-built). Robot-built elements under
the footprint are *blocked*: they cannot be built from that candidate and must
be built after the platform has left it for good.

Coverage is a sparse (candidates x elements) matrix whose entries are bit masks
of the lift levels from which every tool frame of the element is reachable.
Obstacles and elements are treated as full-height prisms in plan view.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from scipy import sparse
from scipy.spatial import cKDTree

from fabflow.design.elements import Element
from fabflow.project import Platform, Site
from fabflow.robots.reach_model import ReachModel

PAIR_CHUNK = 2_000_000
"""Candidate-frame pairs evaluated per batch (bounds memory on large projects)."""


@dataclass(frozen=True, eq=False)
class Candidates:
    """Collision-free candidate platform poses.

    Attributes
    ----------
    xy
        (C, 2) platform origin in the world (metres).
    heading
        (C,) platform heading about world z (radians).
    base_xy
        (C, 2) arm base axis position in the world (metres).
    base_z0
        Height of the arm base above the ground at the lowest lift (metres).
    footprints
        (C,) shapely polygons: footprint grown by the safety margin.
    blocks
        (C,) bool: some robot-built element lies under the footprint.
    outlines
        (U,) plan outlines of the robot-built elements (stacked blocks share one).
    members
        Sparse (U, N) bool: the robot-built elements sharing each outline.
    n_grid
        How many grid poses were generated before collision filtering.
    n_obstructed
        How many of those collided with the site boundary, obstacles or pre-built elements.
    """

    xy: np.ndarray
    heading: np.ndarray
    base_xy: np.ndarray
    base_z0: float
    footprints: np.ndarray
    blocks: np.ndarray
    outlines: np.ndarray
    members: sparse.csr_matrix
    n_grid: int
    n_obstructed: int

    def blocked(self, rows: np.ndarray) -> sparse.csr_matrix:
        """Sparse (len(rows), N) bool: robot-built elements under the footprints of ``rows``."""
        rows = np.asarray(rows, dtype=np.intp)
        U = len(self.outlines)
        if U == 0 or len(rows) == 0:
            return sparse.csr_matrix((len(rows), self.members.shape[1]), dtype=bool)
        hit = shapely.STRtree(self.outlines).query(self.footprints[rows], predicate="intersects")
        H = sparse.csr_matrix(
            (np.ones(hit.shape[1], dtype=np.int32), (hit[0], hit[1])), shape=(len(rows), U)
        )
        out = (H @ self.members.astype(np.int32)).tocsr()
        out.data[:] = 1
        return out.astype(bool)

    def __len__(self) -> int:
        return len(self.xy)

    def T_world_platform(self, i: int) -> np.ndarray:
        """4x4 platform pose of candidate ``i`` (metres)."""
        c, s = math.cos(self.heading[i]), math.sin(self.heading[i])
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = self.xy[i]
        return T


def footprint_corners(
    xy: np.ndarray, heading: np.ndarray, size: tuple[float, float], margin: float
) -> np.ndarray:
    """Corners (C, 4, 2) of platform footprints grown by ``margin`` (metres), counter-clockwise.

    Parameters
    ----------
    xy
        (C, 2) platform origins (metres).
    heading
        (C,) headings (radians).
    size
        Footprint (length along platform x, width along y) in metres, centred on the origin.
    margin
        Safety margin added on every side (metres).
    """
    hx = 0.5 * size[0] + margin
    hy = 0.5 * size[1] + margin
    local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
    c, s = np.cos(heading), np.sin(heading)
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    return np.einsum("cij,kj->cki", R, local) + xy[:, None, :]


def _footprints_with_arm(
    xy: np.ndarray,
    heading: np.ndarray,
    offset: np.ndarray,
    size: tuple[float, float],
    margin: float,
    radius: float,
) -> np.ndarray:
    """Footprints (:func:`footprint_corners`) joined with the disc of ``radius`` the arm's
    base sweeps, ``offset`` ``(C, 2)`` from each platform origin ``xy`` (it turns with
    the heading).

    One union per heading, made at the origin and moved to every platform
    position (GEOS unions are slow one by one; the shape only turns with the
    heading).
    """
    headings, first, which = np.unique(heading, return_index=True, return_inverse=True)
    shapes = shapely.union(
        shapely.polygons(footprint_corners(np.zeros((len(headings), 2)), headings, size, margin)),
        shapely.buffer(shapely.points(offset[first]), radius, quad_segs=8),
    )
    fp = shapes[which.ravel()]
    shift = np.repeat(xy, shapely.get_num_coordinates(fp), axis=0)
    return shapely.transform(fp, lambda coords: coords + shift)


def footprint_polygons(
    xy: np.ndarray, heading: np.ndarray, size: tuple[float, float], margin: float
) -> np.ndarray:
    """Plan-view rectangles (shapely polygons) of platforms grown by ``margin`` on every side.

    See :func:`footprint_corners` for the parameters.
    """
    return shapely.polygons(footprint_corners(xy, heading, size, margin))


def block_corners(elements: Sequence[Element]) -> tuple[np.ndarray, np.ndarray]:
    """Plan-view corners of the blocks among ``elements``.

    Returns
    -------
    index
        (B,) indices of the blocks in ``elements``.
    corners
        (B, 4, 2) corners around each block's outline (metres).
    """
    idx = np.array(
        [i for i, e in enumerate(elements) if e.type == "block" and e.extents is not None],
        dtype=np.intp,
    )
    if len(idx) == 0:
        return idx, np.zeros((0, 4, 2))
    T = np.stack([elements[i].T_world_element for i in idx])
    ext = np.stack([np.asarray(elements[i].extents, dtype=float) for i in idx])
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=float)
    half = 0.5 * ext[:, None, :2] * signs[None]
    corners = (
        T[:, None, :2, 3] + half[..., :1] * T[:, None, :2, 0] + half[..., 1:2] * T[:, None, :2, 1]
    )
    return idx, corners


def obstacle_polygons(site: Site) -> list[shapely.Geometry]:
    """Plan-view polygons of the site obstacles."""
    out = []
    for ob in site.obstacles:
        if ob.box is not None:
            out.append(shapely.box(ob.box.min[0], ob.box.min[1], ob.box.max[0], ob.box.max[1]))
        else:
            assert ob.polygon is not None
            out.append(shapely.make_valid(shapely.Polygon(ob.polygon.points)))
    return out


def element_polygons(elements: Sequence[Element]) -> np.ndarray:
    """Plan-view outlines of elements (blocks: rotated rectangles; print paths: buffered lines).

    Task points have no body and get an empty geometry.
    """
    n = len(elements)
    geoms = np.full(n, None, dtype=object)
    blocks, corners = block_corners(elements)
    if len(blocks):
        geoms[blocks] = shapely.polygons(corners)
    for i, e in enumerate(elements):
        if e.type == "print_path" and e.polyline is not None and len(e.polyline) >= 2:
            pts = np.asarray(e.polyline) @ e.T_world_element[:3, :3].T + e.T_world_element[:3, 3]
            width = float(e.attributes.get("bead_width", 0.03))
            geoms[i] = shapely.buffer(shapely.linestrings(pts[:, :2]), 0.5 * width)
    geoms[[g is None for g in geoms]] = shapely.empty(1)[0]
    return geoms


def unique_outlines(elements: Sequence[Element]) -> tuple[np.ndarray, np.ndarray]:
    """Distinct plan-view outlines of the elements (stacked blocks share one).

    Returns
    -------
    outlines
        (U,) shapely geometries (blocks are merged when their corners agree to 0.1 mm).
    outline_of
        (N,) index into ``outlines`` of every element's outline.
    """
    geoms = element_polygons(elements)
    keys = np.empty(len(geoms), dtype=object)
    blocks, corners = block_corners(elements)
    if len(blocks):
        # A rectangle's key: its corners rounded to 0.1 mm, in sorted order.
        q = np.round(corners * 1e4).astype(np.int64)
        order = np.lexsort((q[..., 1], q[..., 0]), axis=1)
        q = np.take_along_axis(q, order[..., None], axis=1).reshape(len(blocks), 8)
        keys[blocks] = [b"r" + row.tobytes() for row in q]
    others = np.setdiff1d(np.arange(len(geoms)), blocks)
    if len(others):
        wkb = shapely.to_wkb(shapely.normalize(geoms[others]))
        keys[others] = [b"e" if k is None else b"g" + k for k in wkb]
    _, first, outline_of = np.unique(keys, return_index=True, return_inverse=True)
    return geoms[first], outline_of.ravel()


def generate_candidates(
    site: Site,
    platform: Platform,
    elements: Sequence[Element],
    frame_xy: np.ndarray,
    r_max: float,
    spacing: float,
    headings_deg: Sequence[float],
    arm_radius: float = 0.0,
) -> Candidates:
    """Collision-free candidate platform poses near the elements.

    Parameters
    ----------
    site
        Site extent and obstacles (world frame).
    platform
        Footprint, safety margin and arm mounting.
    elements
        All elements (pre-built ones are obstacles, robot-built ones may be blocked).
    frame_xy
        (K, 2) plan positions of the tool frames to build (metres); candidates whose
        arm base is farther than ``r_max`` from all of them are dropped.
    r_max
        Largest horizontal reach of the arm (metres).
    spacing
        Grid spacing (metres).
    headings_deg
        Platform headings to try at every grid point (degrees).
    arm_radius
        Plan radius about the arm's axis 1 that its shoulder sweeps, clearance
        included (metres; :func:`fabflow.robots.geometry.shoulder_radius`): the disc
        joins the footprint, so no pre-built element stands in it and robot-built
        ones in it are built after the platform has left.
    """
    lo = np.asarray(site.extent_min, dtype=float)
    hi = np.asarray(site.extent_max, dtype=float)
    nx = math.floor((hi[0] - lo[0]) / spacing) + 1
    ny = math.floor((hi[1] - lo[1]) / spacing) + 1
    gx = lo[0] + spacing * np.arange(nx)
    gy = lo[1] + spacing * np.arange(ny)
    GX, GY = np.meshgrid(gx, gy, indexing="ij")
    grid = np.stack([GX.ravel(), GY.ravel()], axis=1)
    heads = np.radians(np.asarray(headings_deg, dtype=float))
    xy = np.repeat(grid, len(heads), axis=0)
    heading = np.tile(heads, len(grid))
    n_grid = len(xy)

    T_pb = platform.T_platform_base.matrix()
    c, s = np.cos(heading), np.sin(heading)
    off = T_pb[:2, 3]
    offset = np.stack([c * off[0] - s * off[1], s * off[0] + c * off[1]], axis=1)
    base_xy = xy + offset
    if len(frame_xy):
        d, _ = cKDTree(frame_xy).query(base_xy, distance_upper_bound=r_max)
        near = np.isfinite(d)
    else:
        near = np.zeros(len(xy), dtype=bool)
    xy, heading, offset, base_xy = xy[near], heading[near], offset[near], base_xy[near]

    margin = float(platform.safety_margin)
    fp_corners = footprint_corners(xy, heading, platform.footprint, margin)
    if arm_radius > 0:
        fp = _footprints_with_arm(xy, heading, offset, platform.footprint, margin, arm_radius)
    else:
        fp = shapely.polygons(fp_corners)
    inside = np.all((fp_corners >= lo) & (fp_corners <= hi), axis=(1, 2))

    bad = ~inside
    obstacles = obstacle_polygons(site)
    if obstacles:
        hit = shapely.STRtree(obstacles).query(fp, predicate="intersects")
        bad[hit[0]] = True

    n = len(elements)
    robot_built = np.array([e.robot_built for e in elements], dtype=bool)
    outlines, outline_of = unique_outlines(elements)
    U = len(outlines)
    has_prebuilt = np.bincount(outline_of[~robot_built], minlength=U) > 0
    has_robot = np.bincount(outline_of[robot_built], minlength=U) > 0
    # One merged (prepared) outline per kind: GEOS then tests each footprint
    # against an indexed geometry instead of pair by pair.
    if has_prebuilt.any():
        merged = shapely.union_all(outlines[has_prebuilt])
        shapely.prepare(merged)
        bad |= shapely.intersects(merged, fp)
    blocks = np.zeros(len(fp), dtype=bool)
    if has_robot.any():
        merged = shapely.union_all(outlines[has_robot])
        shapely.prepare(merged)
        blocks = shapely.intersects(merged, fp)

    keep = np.flatnonzero(~bad)
    rb_outlines = np.flatnonzero(has_robot)
    slot = np.full(U, -1)
    slot[rb_outlines] = np.arange(len(rb_outlines))
    rb = np.flatnonzero(robot_built)
    members = sparse.csr_matrix(
        (np.ones(len(rb), dtype=bool), (slot[outline_of[rb]], rb)), shape=(len(rb_outlines), n)
    )
    return Candidates(
        xy=xy[keep],
        heading=heading[keep],
        base_xy=base_xy[keep],
        base_z0=float(T_pb[2, 3]),
        footprints=fp[keep],
        blocks=blocks[keep],
        outlines=outlines[rb_outlines],
        members=members,
        n_grid=n_grid,
        n_obstructed=int(near.sum()) - len(keep),
    )


def lift_levels(lift_range: tuple[float, float], step: float, max_levels: int = 32) -> np.ndarray:
    """Discrete lift heights covering ``lift_range`` (metres), at most ``max_levels``."""
    lo, hi = float(lift_range[0]), float(lift_range[1])
    if hi - lo < 1e-9:
        return np.array([lo])
    n = min(max_levels, math.ceil((hi - lo) / step - 1e-9) + 1)
    return np.linspace(lo, hi, max(n, 2))


def coverage(
    cands: Candidates,
    T_world_tool: np.ndarray,
    owner: np.ndarray,
    n_elements: int,
    reach: ReachModel,
    lifts: np.ndarray,
    rows: np.ndarray | None = None,
) -> sparse.csr_matrix:
    """Which candidate builds which element, and at which lift levels.

    Parameters
    ----------
    cands
        Collision-free candidates.
    T_world_tool
        (K, 4, 4) tool frames in the world (metres); only their positions are used
        (the reach model assumes the tool points down, any yaw).
    owner
        (K,) element index of every frame (non-decreasing).
    n_elements
        Number of elements N.
    reach
        Reach model of the arm.
    lifts
        (L,) lift heights (metres), L <= 32.
    rows
        Only these candidates (default all); the other rows stay empty.

    Returns
    -------
    sparse.csr_matrix
        (C, N) int64 matrix; bit l of entry (c, e) is set when every frame of element
        e is reachable from candidate c at lift ``lifts[l]``. Elements under the
        candidate's footprint are not removed here (see :meth:`Candidates.blocked`).
    """
    C = len(cands)
    if C == 0 or len(T_world_tool) == 0:
        return sparse.csr_matrix((C, n_elements), dtype=np.int64)
    p = T_world_tool[:, :3, 3]
    n_frames = np.bincount(owner, minlength=n_elements)
    single = bool(np.all(n_frames == 1)) and len(owner) == n_elements
    z_rel0 = p[:, 2] - cands.base_z0

    rows = np.arange(C) if rows is None else np.asarray(rows, dtype=np.intp)
    if len(rows) == 0:
        return sparse.csr_matrix((C, n_elements), dtype=np.int64)
    tree_c = cKDTree(cands.base_xy[rows])
    rows_all: list[np.ndarray] = []
    cols_all: list[np.ndarray] = []
    vals_all: list[np.ndarray] = []
    # Batches of frames keep the pair arrays bounded; frames of one element stay together.
    per_frame = max(1.0, tree_c.n * math.pi * reach.r_max**2 / max(_area(cands.base_xy[rows]), 1.0))
    step = max(1, int(PAIR_CHUNK / per_frame))
    start = 0
    K = len(p)
    while start < K:
        stop = min(K, start + step)
        while stop < K and owner[stop] == owner[stop - 1]:
            stop += 1
        sub = cKDTree(p[start:stop, :2])
        pairs = sub.sparse_distance_matrix(tree_c, reach.r_max, output_type="ndarray")
        f = pairs["i"].astype(np.intp) + start
        cand = rows[pairs["j"].astype(np.intp)]
        zr = z_rel0[start:stop, None] - lifts[None, :]
        mask = reach.level_masks(pairs["v"], f - start, zr)
        keep = mask != 0
        f, cand, mask = f[keep], cand[keep], mask[keep]
        e = owner[f]
        if not single and len(f):
            key = cand.astype(np.int64) * n_elements + e
            order = np.argsort(key, kind="stable")
            key, mask = key[order], mask[order]
            first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
            counts = np.diff(np.r_[first, len(key)])
            mask = np.bitwise_and.reduceat(mask, first)
            key = key[first]
            cand = (key // n_elements).astype(np.intp)
            e = (key % n_elements).astype(np.intp)
            full = (counts == n_frames[e]) & (mask != 0)
            cand, e, mask = cand[full], e[full], mask[full]
        rows_all.append(cand)
        cols_all.append(e)
        vals_all.append(mask)
        start = stop
    M = sparse.csr_matrix(
        (np.concatenate(vals_all), (np.concatenate(rows_all), np.concatenate(cols_all))),
        shape=(C, n_elements),
        dtype=np.int64,
    )
    M.sum_duplicates()
    return M


def _area(xy: np.ndarray) -> float:
    span = xy.max(axis=0) - xy.min(axis=0) if len(xy) else np.zeros(2)
    return float(max(span[0], 1.0) * max(span[1], 1.0))
