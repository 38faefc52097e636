"""Grasp pose planning for a two-jaw gripper on a point cloud (paper 002, section 5).

:func:`planning_cloud` builds the planning cloud (section 5.2); :func:`detect_grasps`
samples the object, gives each sample a local reference frame (eq. 4), rotates it in
discrete steps and pushes the open gripper along the approach until it touches the cloud
(section 5.3); :func:`rank_grasps` applies the sequential filter of section 5.4 (eqs.
5-7); :func:`plan_grasp` runs it all and picks the best grasp the machine can reach.

The paper tells force-closure grasps by a CNN (ten Pas et al., 2017). A geometric
antipodal test replaces it here: inside the closing region, the points nearest each jaw
along the closing direction form the contacts, and both outward normals must lie within
the friction cone (half-angle ``atan(mu)``) of the line between the contacts. A grasp
must also hold the object balanced: its centroid within the jaws' width across them and
no deeper along the approach than the deeper contact (an addition to the paper, whose
eq. 7 only ranks by the centroid's distance).

Points, poses and lengths are in metres in the world frame; angles in radians unless a
name ends in ``_deg``. Gripper poses use the frame of :mod:`fabflow.manipulation.gripper`:
``z`` the approach, ``y`` the closing direction, origin between the jaws' tips (the TCP).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import sparse
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from fabflow.errors import InputError
from fabflow.manipulation.antipodal import force_closure
from fabflow.manipulation.gripper import TwoJawGripper, sweep_approach
from fabflow.positioning.pointcloud import as_points, box_mask, estimate_normals, voxel_downsample

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]
Reachability = Callable[[FloatArray, FloatArray], ArrayLike]
"""Callback ``reachable(T_world_gripper (M, 4, 4), opening (M,)) -> (M,) bool`` (the
machine's IK, and whatever the caller checks of where a grasp leads)."""


@dataclass(frozen=True)
class GraspParams:
    """Settings of the grasp planner (metres and degrees).

    Attributes
    ----------
    n_samples
        Points sampled on the object, each the anchor of several hypotheses.
    lrf_radius
        Radius ``r`` of the ball of eq. 4.
    y_rotations_deg, z_rotations_deg
        Rotations about the local frame's ``y`` and ``z``; each pair makes a hypothesis
        ``F Rz(γ) Ry(β)``. About ``z`` (the curvature axis) the approach tilts within the
        closing plane, about ``y`` towards the jaws' width. The wider range about ``z``
        turns samples on a rounded stone's flank (normal 30-60° off vertical) into
        vertical approaches that close across the stone.
    n_align, n_enclose
        Sizes of the two filters of section 5.4 (40 and 20 in the paper).
    friction_coefficient
        ``mu`` of the antipodal test.
    spacing
        Voxel size of the planning cloud.
    contact_tolerance
        A jaw's contact is the points within this distance (along ``y``) of the point
        nearest it.
    standoff
        The gripper stops this far before first touching the cloud.
    opening_clearance
        Added to the width between the contacts to give the pre-grasp opening.
    min_closing_points
        Fewest cloud points the closing region must hold.
    flat_ratio
        Where the middle eigenvalue of eq. 4's matrix is below this fraction of the
        largest, the patch is flat and its curvature axis undefined; the frame's ``z``
        is then the object's longest principal axis projected into the tangent plane,
        so the jaws close across the object's narrower side.
    normal_neighbours
        Neighbours of the PCA normals of the planning cloud.
    max_align_deg
        Hypotheses whose approach is further than this from straight down are dropped
        before the sweep (from below the horizon they would come through the ground).
    """

    n_samples: int = 200
    lrf_radius: float = 0.15
    y_rotations_deg: tuple[float, ...] = (-30.0, 0.0, 30.0)
    z_rotations_deg: tuple[float, ...] = (-60.0, -30.0, 0.0, 30.0, 60.0)
    n_align: int = 40
    n_enclose: int = 20
    friction_coefficient: float = 0.5
    spacing: float = 0.03
    contact_tolerance: float = 0.03
    standoff: float = 0.02
    opening_clearance: float = 0.1
    min_closing_points: int = 10
    flat_ratio: float = 0.05
    normal_neighbours: int = 16
    max_align_deg: float = 90.0

    def __post_init__(self) -> None:
        for name in ("n_samples", "n_align", "n_enclose", "min_closing_points"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise InputError(f"grasp parameter {name} must be a positive integer, got {value}")
        positive = ("lrf_radius", "spacing", "contact_tolerance", "friction_coefficient")
        for name in (*positive, "standoff", "opening_clearance", "flat_ratio"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0 or (value == 0 and name in positive):
                bound = "positive" if name in positive else ">= 0"
                raise InputError(f"grasp parameter {name} must be {bound}, got {value}")
        if self.normal_neighbours < 3 or not self.y_rotations_deg or not self.z_rotations_deg:
            raise InputError("grasp parameters need normal_neighbours >= 3 and some rotations")
        if not 0 < self.max_align_deg <= 180:
            raise InputError(f"max_align_deg must be in (0, 180], got {self.max_align_deg}")


@dataclass(frozen=True, eq=False)
class PlanningCloud:
    """The grasp planning cloud (world frame, metres).

    Attributes
    ----------
    points
        ``(N, 3)`` downsampled points.
    normals
        ``(N, 3)`` unit normals, pointing away from the object's centroid on the object
        and along the ground's upward normal elsewhere.
    object_mask
        ``(N,)`` true for points of the object to grasp.
    ground_plane
        ``(a, b, c, d)`` with ``(a, b, c)`` the unit upward normal: ``n·p + d = 0``.
    """

    points: FloatArray
    normals: FloatArray
    object_mask: BoolArray
    ground_plane: FloatArray


@dataclass(frozen=True, eq=False)
class GraspSet:
    """Grasp candidates and their costs (eqs. 5-7).

    Attributes
    ----------
    T_world_gripper
        ``(K, 4, 4)`` gripper poses (metres).
    opening
        ``(K,)`` pre-grasp openings between the jaws' inner faces (metres).
    contacts
        ``(K, 2, 3)`` contact points of the ``+y`` and the ``-y`` jaw (world, metres).
    c_align
        ``(K,)`` angle between the approach and straight down (radians, eq. 5).
    c_enclose
        ``(K,)`` distance from the palm centre to the centroid along the approach
        (metres, eq. 6); smaller is a deeper, more enclosing grasp.
    c_dist
        ``(K,)`` distance from the centroid to the approach line through the TCP
        (metres, eq. 7).
    """

    T_world_gripper: FloatArray
    opening: FloatArray
    contacts: FloatArray
    c_align: FloatArray
    c_enclose: FloatArray
    c_dist: FloatArray

    def __len__(self) -> int:
        return len(self.opening)

    @classmethod
    def from_poses(
        cls,
        T_world_gripper: ArrayLike,
        opening: ArrayLike,
        contacts: ArrayLike,
        centroid: ArrayLike,
        ground_normal: ArrayLike,
        gripper: TwoJawGripper,
    ) -> GraspSet:
        """Build a set from poses, computing the costs with :func:`grasp_costs`."""
        T = np.asarray(T_world_gripper, dtype=float).reshape(-1, 4, 4)
        costs = grasp_costs(T, centroid, ground_normal, gripper)
        return cls(
            T,
            np.asarray(opening, dtype=float).reshape(len(T)),
            np.asarray(contacts, dtype=float).reshape(len(T), 2, 3),
            *costs,
        )


@dataclass(frozen=True, eq=False)
class GraspPlan:
    """The result of :func:`plan_grasp`.

    ``cloud`` is the planning cloud, ``grasps`` all force-closure candidates, ``ranking``
    indices into ``grasps`` best first (all of them, see :func:`rank_grasps`),
    ``reachable`` whether the machine reaches each ranked grasp, ``chosen`` the index into
    ``grasps`` of the chosen grasp (``None`` when there is none) and ``reason`` why none
    was chosen (empty when one was).
    """

    cloud: PlanningCloud
    grasps: GraspSet
    ranking: IntArray
    reachable: BoolArray
    chosen: int | None
    reason: str = ""

    def candidate_rows(self) -> list[dict[str, Any]]:
        """The ranked candidates as JSON-able rows, best first.

        Each row holds ``T_world_gripper`` (4x4 nested list, metres), ``opening_m``,
        ``c_align_rad``, ``c_enclose_m``, ``c_dist_m``, ``rank`` (0 is best) and
        ``reachable``.
        """
        g = self.grasps
        return [
            {
                "T_world_gripper": g.T_world_gripper[i].tolist(),
                "opening_m": float(g.opening[i]),
                "c_align_rad": float(g.c_align[i]),
                "c_enclose_m": float(g.c_enclose[i]),
                "c_dist_m": float(g.c_dist[i]),
                "rank": rank,
                "reachable": bool(self.reachable[rank]),
            }
            for rank, i in enumerate(self.ranking.tolist())
        ]


def _point(value: ArrayLike, name: str) -> FloatArray:
    p = np.asarray(value, dtype=float).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"{name} must be a finite 3-vector, got {value!r}")
    return p


def _object_points(object_points: ArrayLike) -> FloatArray:
    o = as_points(object_points, "object_points")
    if len(o) < 3:
        raise InputError(f"need at least 3 object points, got {len(o)}")
    return o


def _ground(ground_plane: ArrayLike) -> FloatArray:
    """``(a, b, c, d)`` normalized to a unit normal pointing up (``c > 0``)."""
    g = np.asarray(ground_plane, dtype=float).reshape(-1)
    if g.shape != (4,) or not np.all(np.isfinite(g)):
        raise InputError(f"ground_plane must be (a, b, c, d), got {ground_plane!r}")
    norm = np.linalg.norm(g[:3])
    if norm == 0 or abs(g[2]) < 0.5 * norm:
        raise InputError(f"ground_plane {g.tolist()} is not within 60° of horizontal")
    return g / norm * np.sign(g[2])


def grasp_costs(
    T_world_gripper: ArrayLike,
    centroid: ArrayLike,
    ground_normal: ArrayLike,
    gripper: TwoJawGripper,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The costs of eqs. 5-7 of paper 002 for gripper poses.

    ``n_approach`` is the poses' ``z``, ``n_ground`` the ground's upward normal and
    ``r_CoM`` runs from the palm centre (``jaw_length`` behind the TCP) to the centroid.

    Returns
    -------
    c_align, c_enclose, c_dist
        ``(K,)`` each: ``arccos(-n_ground·n_approach)`` (radians, 0 for a vertical
        approach from above), ``r_CoM·n_approach`` (metres, shrinking as the palm comes
        closer to the centroid) and ``|r_CoM × n_approach|`` (metres).
    """
    T = np.asarray(T_world_gripper, dtype=float).reshape(-1, 4, 4)
    n = _point(ground_normal, "ground_normal")
    n = n / np.linalg.norm(n)
    z = T[:, :3, 2]
    palm = T[:, :3, 3] - gripper.jaw_length * z
    r = _point(centroid, "centroid")[None] - palm
    c_align = np.arccos(np.clip(-(z @ n), -1.0, 1.0))
    c_enclose = np.einsum("ij,ij->i", r, z)
    c_dist = np.linalg.norm(np.cross(r, z), axis=1)
    return c_align, c_enclose, c_dist


def planning_cloud(
    map_points: ArrayLike,
    object_points: ArrayLike,
    centroid: ArrayLike,
    gripper: TwoJawGripper,
    ground_plane: ArrayLike,
    spacing: float = 0.03,
    normal_neighbours: int = 16,
) -> PlanningCloud:
    """The grasp planning cloud around one object (section 5.2, figs. 5 and 6).

    The map (``(N, 3)``, may be empty) is cropped to the bounding box of the object's
    registered model points (``(M, 3)``, M >= 3) and centroid, grown on every side by the
    gripper's full width (``palm_span``), and merged with the model points. Grid points
    on ``ground_plane`` (``(a, b, c, d)``, ``n·p + d = 0``, e.g. from
    :func:`fabflow.positioning.segmentation.ransac_plane`) fill every place of the crop
    with no point within ``2 * spacing`` (the holes the object's occlusion leaves). The
    result is downsampled to ``spacing``; points within ``2 * spacing`` of a model point
    and more than ``spacing`` above the ground form the object. All in world metres.
    """
    o = _object_points(object_points)
    m = as_points(map_points, "map_points")
    c = _point(centroid, "centroid")
    plane = _ground(ground_plane)
    if not np.isfinite(spacing) or spacing <= 0:
        raise InputError(f"spacing must be a positive length in metres, got {spacing}")
    margin = gripper.palm_span
    lo = np.minimum(o.min(axis=0), c) - margin
    hi = np.maximum(o.max(axis=0), c) + margin
    merged = np.vstack([m[box_mask(m, lo, hi)], o])
    filled = np.vstack([merged, _ground_fill(merged, plane, lo, hi, spacing)])
    points, _ = voxel_downsample(filled, spacing)
    height = points @ plane[:3] + plane[3]
    near, _ = cKDTree(o).query(points, distance_upper_bound=2.0 * spacing, workers=-1)
    object_mask = np.isfinite(near) & (height > spacing)
    normals = np.asarray(estimate_normals(points, k=normal_neighbours))
    outward = np.where(object_mask[:, None], points - c, plane[:3])
    normals[np.einsum("ij,ij->i", normals, outward) < 0] *= -1.0
    return PlanningCloud(points, normals, object_mask, plane)


def _ground_fill(
    cloud: FloatArray, plane: FloatArray, lo: FloatArray, hi: FloatArray, spacing: float
) -> FloatArray:
    """Grid points on the ground plane inside the box, where ``cloud`` has none near."""
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], spacing), np.arange(lo[1], hi[1], spacing))
    gz = -(plane[0] * gx + plane[1] * gy + plane[3]) / plane[2]
    grid = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])
    grid = grid[(grid[:, 2] >= lo[2]) & (grid[:, 2] <= hi[2])]
    if len(cloud) == 0:
        return grid
    d, _ = cKDTree(cloud).query(grid, distance_upper_bound=2.0 * spacing, workers=-1)
    return grid[~np.isfinite(d)]


def _local_frames(
    points: FloatArray,
    normals: FloatArray,
    samples: IntArray,
    object_axes: FloatArray,
    params: GraspParams,
) -> FloatArray:
    """Local reference frames ``(S, 3, 3)`` (columns x, y, z) of eq. 4 at the samples.

    ``x`` is the eigenvector of the largest eigenvalue of ``Σ n nᵀ`` over the r-ball,
    signed along the sample's outward normal; ``z`` that of the smallest (the axis of
    least curvature; the paper writes ``F = [ν3, ν2, ν1]`` with its own numbering);
    ``y = z × x``. On flat patches ``z`` is the object's principal axis instead.
    """
    tree = cKDTree(points)
    pairs = cKDTree(points[samples]).sparse_distance_matrix(
        tree, params.lrf_radius, output_type="ndarray"
    )
    ball = sparse.csr_matrix(
        (np.ones(len(pairs)), (pairs["i"], pairs["j"])), shape=(len(samples), len(points))
    )
    outer = (normals[:, :, None] * normals[:, None, :]).reshape(-1, 9)
    evals, evecs = np.linalg.eigh((ball @ outer).reshape(-1, 3, 3))
    x = evecs[:, :, 2]
    x *= np.where(np.einsum("ij,ij->i", x, normals[samples]) < 0, -1.0, 1.0)[:, None]
    z = evecs[:, :, 0]
    flat = evals[:, 1] < params.flat_ratio * evals[:, 2]
    proj = object_axes[None, :, :] - np.einsum("si,ai->sa", x, object_axes)[:, :, None] * x[:, None]
    longest_fits = np.linalg.norm(proj[:, 0], axis=1) >= 0.5
    fallback = np.where(longest_fits[:, None], proj[:, 0], proj[:, 1])
    z = np.where(flat[:, None], fallback, z)
    y = np.cross(z, x)
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    return np.stack([x, y, np.cross(x, y)], axis=2)


def _rotations(params: GraspParams) -> FloatArray:
    """``(O, 3, 3)`` rotations ``Rz(γ) Ry(β)`` for every pair of steps."""
    gamma, beta = np.meshgrid(params.z_rotations_deg, params.y_rotations_deg, indexing="ij")
    angles = np.column_stack([gamma.ravel(), beta.ravel()])
    return Rotation.from_euler("ZY", angles, degrees=True).as_matrix()


def _evaluate(
    points: FloatArray,
    cloud: PlanningCloud,
    anchors: FloatArray,
    G: FloatArray,
    gripper: TwoJawGripper,
    params: GraspParams,
) -> tuple[BoolArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Sweep, closing-region count and antipodal test: ``(ok, s, contacts, v_max, v_min,
    reach)`` as :func:`~fabflow.manipulation.gripper.sweep_approach` and
    :func:`~fabflow.manipulation.antipodal.force_closure`."""
    s, k, j, v = sweep_approach(points, anchors, G, gripper, params.standoff)
    count = np.bincount(k, minlength=len(G))
    ok, contacts, v_max, v_min, reach = force_closure(
        cloud.points,
        cloud.normals,
        cloud.object_mask,
        (k, j, v),
        G[:, :, 2],
        params.contact_tolerance,
        params.friction_coefficient,
    )
    ok &= np.isfinite(s) & (count >= params.min_closing_points)
    return ok, s, contacts, v_max, v_min, reach


def detect_grasps(
    cloud: PlanningCloud,
    object_points: ArrayLike,
    centroid: ArrayLike,
    gripper: TwoJawGripper,
    rng: np.random.Generator,
    params: GraspParams = GraspParams(),
) -> GraspSet:
    """Force-closure grasp candidates on the object of a planning cloud (section 5.3).

    ``rng`` draws ``n_samples`` points of the cloud's object more than ``2 * spacing``
    above the ground; the object's model points (world, metres) give the principal axis
    of flat patches. A hypothesis approaches along ``-x`` of its rotated local frame
    (into the object), closes along its ``y`` and has the jaws' width along its ``z``;
    the gripper is open at ``max_opening`` while approaching. Kept are the hypotheses
    that touch the cloud, hold at least ``min_closing_points`` points in their closing
    region and pass the antipodal test. Each is then shifted along ``y`` to centre the
    jaws on the extreme points between them (the jaws close symmetrically) and swept
    again, the centred pose kept when it still passes. The opening is twice the larger
    distance of those points from the TCP plus ``opening_clearance``, clipped to the
    gripper's range. Last, a grasp must hold the object balanced: the centroid within the
    jaws' width and no deeper along the approach than the deepest point of either
    contact patch.
    """
    c = _point(centroid, "centroid")
    o = _object_points(object_points)
    points = cloud.points - c  # local coordinates keep float32 exact enough far from 0
    n_up = cloud.ground_plane[:3]
    height = cloud.points @ n_up + cloud.ground_plane[3]
    candidates = np.flatnonzero(cloud.object_mask & (height > 2.0 * params.spacing))
    samples = rng.choice(candidates, min(params.n_samples, len(candidates)), replace=False)
    axes = np.linalg.eigh(np.cov((o - c).T))[1][:, ::-1].T
    frames = _local_frames(points, cloud.normals, samples, axes, params)
    rotations = _rotations(params)
    rotated = (frames[:, None] @ rotations[None]).reshape(-1, 3, 3)
    G = np.stack([rotated[:, :, 2], rotated[:, :, 1], -rotated[:, :, 0]], axis=2)
    anchors = np.repeat(points[samples], len(rotations), axis=0)
    upright = -(G[:, :, 2] @ n_up) >= np.cos(np.radians(params.max_align_deg)) - 1e-12
    ok, s, contacts, v_max, v_min, reach = _evaluate(
        points, cloud, anchors[upright], G[upright], gripper, params
    )
    G, anchors = G[upright][ok], anchors[upright][ok]
    s, contacts, v_max, v_min, reach = s[ok], contacts[ok], v_max[ok], v_min[ok], reach[ok]
    centred = anchors + ((v_max + v_min) / 2.0)[:, None] * G[:, :, 1]
    ok_c, s_c, contacts_c, v_max_c, v_min_c, reach_c = _evaluate(
        points, cloud, centred, G, gripper, params
    )
    anchors = np.where(ok_c[:, None], centred, anchors)
    s = np.where(ok_c, s_c, s)
    contacts = np.where(ok_c[:, None, None], contacts_c, contacts)
    reach = np.where(ok_c, reach_c, reach)
    half_width = np.where(ok_c, np.maximum(-v_min_c, v_max_c), np.maximum(-v_min, v_max))
    T = np.tile(np.eye(4), (len(G), 1, 1))
    T[:, :3, :3] = G
    T[:, :3, 3] = c + anchors + s[:, None] * G[:, :, 2]
    opening = np.clip(
        2.0 * half_width + params.opening_clearance, gripper.min_opening, gripper.max_opening
    )
    # balanced: the centroid within the jaws' width, else the object turns out of them,
    # and no deeper along the approach than the contacts reach, else the jaws pinch the
    # object's near end and it tips out as it is lifted
    r = np.einsum("ki,kij->kj", c - T[:, :3, 3], G)
    depth = reach - np.einsum("ki,ki->k", T[:, :3, 3], G[:, :, 2])
    keep = (np.abs(r[:, 0]) <= gripper.jaw_width / 2) & (r[:, 2] <= depth)
    return GraspSet.from_poses(T[keep], opening[keep], contacts[keep], c, n_up, gripper)


def rank_grasps(grasps: GraspSet, params: GraspParams = GraspParams()) -> IntArray:
    """Rank grasps by the sequential filter of section 5.4, best first.

    Of the candidates sorted by ``c_align``, the first ``n_align`` are taken, the
    ``n_enclose`` of them with the smallest ``c_enclose`` kept and sorted by ``c_dist``:
    that block is the paper's ranking, its first entry the paper's choice. The same
    filter applied again to the candidates left gives the next block, and so on, so the
    ranking orders every candidate (a fallback when the best are out of reach).
    """
    remaining = np.argsort(grasps.c_align, kind="stable")
    blocks = []
    while len(remaining):
        window = remaining[: params.n_align]
        best = window[np.argsort(grasps.c_enclose[window], kind="stable")[: params.n_enclose]]
        blocks.append(best[np.argsort(grasps.c_dist[best], kind="stable")])
        remaining = remaining[~np.isin(remaining, best)]
    return np.concatenate(blocks) if blocks else np.zeros(0, dtype=np.int64)


def plan_grasp(
    map_points: ArrayLike,
    object_points: ArrayLike,
    centroid: ArrayLike,
    ground_plane: ArrayLike,
    gripper: TwoJawGripper,
    rng: np.random.Generator,
    params: GraspParams = GraspParams(),
    reachable: Reachability | None = None,
) -> GraspPlan:
    """Plan a grasp of one object: cloud, detection, ranking and reachability.

    The arguments are those of :func:`planning_cloud` and :func:`detect_grasps` (world,
    metres; seed ``rng`` for a repeatable plan). ``reachable(T_world_gripper (M, 4, 4),
    opening (M,)) -> (M,) bool`` runs the machine's inverse kinematics (and any check of
    where the grasp leads) and is called once with every ranked pose and its jaw
    opening; ``None`` counts all reachable. ``chosen`` is the best-ranked reachable
    grasp; when no force-closure grasp exists or none is reachable it is ``None`` and
    ``reason`` says which (a property of the scene, so no exception).

    Raises
    ------
    InputError
        For malformed inputs, or a ``reachable`` that does not return one boolean per
        pose.
    """
    neighbours = params.normal_neighbours
    cloud = planning_cloud(
        map_points, object_points, centroid, gripper, ground_plane, params.spacing, neighbours
    )
    grasps = detect_grasps(cloud, object_points, centroid, gripper, rng, params)
    ranking = rank_grasps(grasps, params)
    if len(ranking) == 0:
        reason = "no collision-free force-closure grasp found on the object"
        return GraspPlan(cloud, grasps, ranking, np.zeros(0, dtype=bool), None, reason)
    if reachable is None:
        mask = np.ones(len(ranking), dtype=bool)
    else:
        mask = np.asarray(reachable(grasps.T_world_gripper[ranking], grasps.opening[ranking]))
        if mask.shape != (len(ranking),) or mask.dtype != bool:
            raise InputError(
                f"reachable must return ({len(ranking)},) booleans, got {mask.dtype} {mask.shape}"
            )
    if not mask.any():
        reason = f"none of the {len(ranking)} force-closure grasps is reachable"
        return GraspPlan(cloud, grasps, ranking, mask, None, reason)
    return GraspPlan(cloud, grasps, ranking, mask, int(ranking[np.argmax(mask)]))
