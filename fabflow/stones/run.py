"""One stone wall run: scan, perceive, and for each slot grasp, carry, release, re-scan.

The site is simulated (:mod:`fabflow.sensors.stone_scene`): the stones lie on
uneven ground where the stockpile puts them, and the machine knows of them only
what its scans (and the drone's reconstruction) show. Each slot, in the order the
project gives them:

1. the object for the slot (:func:`~fabflow.stones.placing.assign_slots`, once
   for all slots after the first perception); when it has no reachable grasp,
   the spare stones are tried in the order they fit the slot;
2. grasp pose planning on the planning cloud (map, object model, filled
   ground), the ranked candidates filtered by the machine's reach at the grasp
   and at a release in the slot (:mod:`fabflow.stones.placing`);
3. the grasp: the object database records the gripper pose, the map loses its
   points within ``R_obj`` of the object;
4. the release: eq. 3 moves the object in the database; in the simulated world
   the stone moves with the gripper as a rigid body (no settling), the grasp
   and the release each executed off by the machine's repeatability
   (``simulation.robot_repeatability`` per axis);
5. a re-scan from the swing poses, merged into the map, and ICP re-aligns the
   object's model with it (a ``detected`` event).

The simulated truth is used only to score the run (:class:`PickResult`), never
by the pipeline.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from fabflow.design.specs import StoneSlot, StoneWallSpec
from fabflow.manipulation.grasp import GraspPlan, plan_grasp
from fabflow.manipulation.grasp_check import GraspOutcome, grasp_outcome
from fabflow.manipulation.gripper import TwoJawGripper, count_points_in_gripper
from fabflow.manipulation.objects import (
    FoundObject,
    ObjectDatabase,
    grasp,
    realign,
    release,
    remove_object_points,
)
from fabflow.positioning.icp import icp, prepare_target
from fabflow.positioning.pointcloud import voxel_downsample
from fabflow.project import Project
from fabflow.robots.catalog import get_robot
from fabflow.sensors.stone_scene import (
    StoneSite,
    cabin_swing_poses,
    scan_site,
    stone_site,
    uneven_ground,
    vision_map,
)
from fabflow.stones.perception import Perception, lidar_map, perceive
from fabflow.stones.placing import (
    assign_slots,
    choose_release,
    release_poses,
    size_misfit,
    stone_mass,
    target_poses,
)
from fabflow.transforms.se3 import inv_T
from fabflow.transforms.so3 import matrix_from_abc

FloatArray = NDArray[np.float64]

CLEARANCE = 0.6
"""Distance the gripper approaches a grasp and a release from, and lifts (metres)."""
GROUND_MARGIN = 6.0
"""The simulated ground reaches this far beyond the stockpile, the machine and the
slots (metres)."""
RELEASE_CHECK_RADIUS = 2.0
"""Map points this close to a slot's target are checked against the gripper at release
(metres): the open gripper reaches about 1.3 m from its tool centre point."""
RELEASE_CHECK_VOXEL = 0.05
"""The map is thinned to this grid for the release check (metres; the jaws are 8 cm
thick)."""
RELEASE_OPENING = 0.1
"""The jaws open by this much beyond the grasp's opening to let the stone go (metres)."""
TRUTH_SAMPLES = 20_000
"""Surface samples of a true stone that its model is aligned to for scoring."""
RESCAN_HALF_WIDTH_DEG = 40.0
"""After a release the cabin scans the swing's yaws within this angle of the slot."""
VISION_OFFSET = (12.0, -7.0, 0.4, 35.0)
"""The drone reconstruction's own frame: the world shifted by x, y, z (metres) and
turned about z (degrees): a map built without GPS has its own origin."""


@dataclass(frozen=True, eq=False)
class PickResult:
    """One slot's pick and place.

    Attributes
    ----------
    slot
        The slot id.
    object_id
        The object chosen for it (-1: none left).
    plan
        The grasp plan, or ``None`` when there was no object.
    T_grasp, T_release
        4x4 gripper poses (world, metres), ``None`` without a reachable grasp.
    T_target
        4x4 the object's pose in the slot (world), ``None`` without a grasp.
    T_object
        4x4 the object's pose (world) when it was grasped, ``None`` without a grasp.
    opening
        Jaw opening of the grasp (metres).
    reason
        Why the slot was not filled, or ``""``.
    passed_over
        ``(object id, why)`` of the stones tried for the slot before, in order, that
        had no reachable grasp (or were too heavy): the slot's assigned stone, then
        the spare stones by how well they fit.
    stone
        Index of the true stone grasped (simulation truth; -1 none).
    outcome
        The grasp's simulated outcome (truth), ``None`` without a grasp.
    placement_error
        Distance from where the object's frame truly is after the release (the
        model aligned to the true stone, :func:`true_object_pose`) to its target
        in the slot (metres; truth), ``nan`` without a grasp.
    realign_rmse
        ICP RMSE of the re-alignment after the re-scan (metres; ``inf`` refused).
    """

    slot: str
    object_id: int
    plan: GraspPlan | None
    T_grasp: FloatArray | None = None
    T_release: FloatArray | None = None
    T_target: FloatArray | None = None
    T_object: FloatArray | None = None
    opening: float = 0.0
    reason: str = ""
    passed_over: tuple[tuple[int, str], ...] = ()
    stone: int = -1
    outcome: GraspOutcome | None = None
    placement_error: float = float("nan")
    realign_rmse: float = float("inf")


@dataclass(frozen=True, eq=False)
class StoneRun:
    """A whole run: the first perception, every pick and the final state.

    Attributes
    ----------
    perception
        The first perception (segmentation, registration, objects).
    registration_success
        The paper's criterion (section 6.2): the ICP RMSE below ``e*_icp`` and
        every stone detected as one object (simulation truth).
    registration_error_m
        Translation error of the vision map's registration (metres; truth), ``nan``
        when it was rejected.
    picks
        One per slot.
    db
        The object database at the end.
    map_points
        The LiDAR map at the end (metres, world).
    site, site_initial
        The simulated site at the end and at the start (truth).
    T_world_base
        The machine's base pose (world).
    swing
        ``(M, 4, 4)`` LiDAR poses of the scanning swing (world).
    """

    perception: Perception
    registration_success: bool
    registration_error_m: float
    picks: list[PickResult]
    db: ObjectDatabase
    map_points: FloatArray
    site: StoneSite
    site_initial: StoneSite
    T_world_base: FloatArray
    swing: FloatArray


def machine_base(project: Project, spec: StoneWallSpec) -> FloatArray:
    """The arm's base pose in the world: the station, then the platform's mounting."""
    return spec.station.matrix() @ project.robot.platform.T_platform_base.matrix()


def reach_check(
    project: Project, T_world_base: FloatArray
) -> Callable[[FloatArray], NDArray[np.bool_]]:
    """A function telling which gripper poses (world, ``(K, 4, 4)``) the arm reaches."""
    robot = get_robot(project.robot.name)
    T_base_world = inv_T(T_world_base)
    T_tool_flange = inv_T(project.robot.tool.T_flange_tool.matrix())

    def reachable(T_world_tool: FloatArray) -> NDArray[np.bool_]:
        T = np.asarray(T_world_tool, dtype=float).reshape(-1, 4, 4)
        if len(T) == 0:
            return np.zeros(0, dtype=bool)
        _, valid = robot.ik_batch(T_base_world @ T @ T_tool_flange)
        return valid.any(axis=1)

    return reachable


def _vision_frame() -> FloatArray:
    x, y, z, yaw = VISION_OFFSET
    T = np.eye(4)
    T[:3, :3] = matrix_from_abc(np.radians(yaw), 0.0, 0.0)
    T[:3, 3] = (x, y, z)
    return T


def _stone_owners(site: StoneSite, points: FloatArray) -> NDArray[np.intp]:
    """The true stone nearest each point (-1 for the ground: farther than 5 cm from all)."""
    owner = np.full(len(points), -1, dtype=np.intp)
    best = np.full(len(points), 0.05)
    for k in range(len(site.T_world_stone)):
        mesh = site.stone_mesh(k)
        samples = mesh.sample(4000, return_index=False) if len(mesh.faces) else np.zeros((0, 3))
        d, _ = cKDTree(np.vstack([samples, mesh.vertices])).query(points)
        closer = d < best
        owner[closer], best[closer] = k, d[closer]
    return owner


def true_object_pose(obj: FoundObject, stone: trimesh.Trimesh) -> FloatArray:
    """Where the object's model truly lies: aligned by ICP to the true stone's surface.

    The model at its believed pose is registered to noise-free samples of the
    simulated stone's mesh (world frame): the result is the pose the object
    frame would have were the perception exact (simulation truth, metres).
    """
    samples, _ = trimesh.sample.sample_surface(stone, TRUTH_SAMPLES, seed=0)
    res = icp(
        obj.world_points(),
        prepare_target(np.asarray(samples, dtype=float)),
        max_correspondence_distance=(0.2, 0.05, 0.02),
        kernel="huber",
    )
    return res.T @ obj.T_world_object


def clear_of(
    map_points: FloatArray, target: FloatArray, gripper: TwoJawGripper
) -> Callable[[FloatArray, FloatArray], NDArray[np.bool_]]:
    """A check that the open gripper at release poses holds no map point in its boxes.

    The map within :data:`RELEASE_CHECK_RADIUS` of the target (the neighbours set
    before, the ground) is tested against the jaws opened by
    :data:`RELEASE_OPENING` beyond the grasp's opening, and the palm.
    """
    near = map_points[np.linalg.norm(map_points - target, axis=1) <= RELEASE_CHECK_RADIUS]
    near = voxel_downsample(near, RELEASE_CHECK_VOXEL)[0] if len(near) else near

    def free(T: FloatArray, openings: FloatArray) -> NDArray[np.bool_]:
        widths = np.minimum(openings + RELEASE_OPENING, gripper.max_opening)
        return count_points_in_gripper(gripper, T, widths, near) == 0

    return free


def executed(T: FloatArray, sigma: float, rng: np.random.Generator) -> FloatArray:
    """A commanded tool pose as the machine reaches it: off by ``sigma`` per axis (metres)."""
    done = np.array(T, dtype=float)
    done[:3, 3] += rng.normal(0.0, sigma, 3)
    return done


def _single_objects(site: StoneSite, perception: Perception) -> bool:
    """Every stone is exactly one segment, and each segment one stone (>= 90 % of its points)."""
    segments = perception.objects.segments
    if len(segments) != len(site.T_world_stone):
        return False
    seen = set()
    for s in segments:
        owner = _stone_owners(site, s.points)
        counts = np.bincount(owner[owner >= 0], minlength=len(site.T_world_stone))
        k = int(np.argmax(counts))
        if counts[k] < 0.9 * len(owner) or k in seen:
            return False
        seen.add(k)
    return True


def swing_yaws(spec: StoneWallSpec) -> FloatArray:
    """The cabin's yaws of the scanning swing (degrees about the base's z)."""
    lo, hi = spec.swing_deg
    return np.arange(lo, hi + 1e-9, spec.swing_step_deg)


def rescan_yaws(spec: StoneWallSpec, T_world_base: FloatArray, point: FloatArray) -> FloatArray:
    """The swing's yaws within :data:`RESCAN_HALF_WIDTH_DEG` of the direction to ``point``."""
    local = inv_T(T_world_base) @ np.append(point, 1.0)
    bearing = np.degrees(np.arctan2(local[1], local[0]))
    yaws = swing_yaws(spec)
    off = (yaws - bearing + 180.0) % 360.0 - 180.0
    near = yaws[np.abs(off) <= RESCAN_HALF_WIDTH_DEG]
    return near if len(near) else yaws[[int(np.argmin(np.abs(off)))]]


def within_reach(
    reachable: Callable[[FloatArray], NDArray[np.bool_]], centroids: FloatArray
) -> NDArray[np.bool_]:
    """Whether the gripper reaches each centroid from straight above (world ``(K, 3)``)."""
    T = np.tile(np.diag([1.0, -1.0, -1.0, 1.0]), (len(centroids), 1, 1))  # z down
    T[:, :3, 3] = centroids
    return reachable(T)


def _plan_pick(
    project: Project,
    obj: FoundObject,
    slot: StoneSlot,
    map_points: FloatArray,
    ground: FloatArray,
    gripper: TwoJawGripper,
    reachable: Callable[..., NDArray[np.bool_]],
    rng: np.random.Generator,
) -> tuple[
    GraspPlan | None, FloatArray, Callable[[FloatArray, FloatArray], NDArray[np.bool_]], str
]:
    """Grasp plan of ``obj`` for ``slot``: ``(plan, targets, free, why)``.

    ``targets`` are the object's fitting poses in the slot, ``free`` the release
    check (:func:`clear_of`); ``why`` says why there is no reachable
    grasp (``plan`` is ``None`` for a stone too heavy to lift), else it is empty.
    """
    targets = target_poses(obj, slot.pose.matrix(), slot.size)
    free = clear_of(map_points, targets[0, :3, 3], gripper)
    mass = stone_mass(obj)
    payload = get_robot(project.robot.name).payload
    if mass + project.robot.tool.mass > payload:
        why = (
            f"it weighs about {mass:.0f} kg: with the tool more than the "
            f"machine's rated payload of {payload:g} kg"
        )
        return None, targets, free, why

    def fits(G: FloatArray, widths: FloatArray) -> NDArray[np.bool_]:
        return choose_release(obj.T_world_object, G, targets, reachable, CLEARANCE, free, widths)[0]

    plan = plan_grasp(
        map_points, obj.world_points(), obj.centroid, ground, gripper, rng, reachable=fits
    )
    why = "" if plan.chosen is not None else plan.reason
    return plan, targets, free, why


def run_stone_wall(
    project: Project,
    seed: int | None = None,
    on_slot: Callable[[str], None] | None = None,
) -> StoneRun:
    """Build the stone wall in simulation, from scans only (module docstring).

    Parameters
    ----------
    project
        A project whose only element source is a ``stone_wall``.
    seed
        Seed of the site and of every draw (default: the stockpile's seed).
    on_slot
        Called with each slot's id before it is worked on (progress).
    """
    spec = project.stone_wall()
    if spec is None:
        raise ValueError("run_stone_wall needs a project with a stone_wall")
    pile = spec.stockpile
    rng = np.random.default_rng(pile.seed if seed is None else seed)
    T_world_base = machine_base(project, spec)
    slots = np.array([s.pose.xyz[:2] for s in spec.slots])
    corners = np.vstack([pile.region_min, pile.region_max, T_world_base[:2, 3], slots])
    ground = uneven_ground(
        rng,
        corners.min(axis=0) - GROUND_MARGIN,
        corners.max(axis=0) + GROUND_MARGIN,
        amplitude=pile.terrain_rms,
        wavelength=pile.terrain_wavelength,
    )
    site = stone_site(
        rng,
        ground=ground,
        n_stones=pile.n_stones,
        region_min=pile.region_min,
        region_max=pile.region_max,
        volume_range=pile.volume_range,
        convex_share=pile.convex_share,
    )
    site_initial = site
    swing = cabin_swing_poses(T_world_base, swing_yaws(spec))
    scans = scan_site(site, swing, rng)
    vision = vision_map(site, rng, T_source_world=_vision_frame()) if spec.vision_map else None
    centre = T_world_base[:3, 3]
    perception = perceive(lidar_map(scans.points_world, centre), rng, vision)
    reg_error = float("nan")
    if perception.registration is not None:
        T_err = perception.registration.T_target_source @ _vision_frame()
        reg_error = float(np.linalg.norm(T_err[:3, 3]))
    rmse_ok = perception.registration is not None or not spec.vision_map
    registration_success = rmse_ok and _single_objects(site, perception)

    db = perception.db
    map_points = perception.map_points
    ground = perception.ground_plane
    reachable = reach_check(project, T_world_base)
    sigma = project.simulation.robot_repeatability
    gripper = TwoJawGripper()
    # the stones the gripper reaches from above; the others stay where they lie
    objects = [o for o in db.objects if within_reach(reachable, o.centroid[None])[0]]
    sizes = np.array([s.size for s in spec.slots]).reshape(-1, 3)
    extents = np.array([o.extents for o in objects]).reshape(-1, 3)
    assignment = assign_slots(extents, sizes)
    spare = [i for i in range(len(objects)) if i not in set(assignment.tolist())]
    picks: list[PickResult] = []
    for k, (slot, pick) in enumerate(zip(spec.slots, assignment, strict=True)):
        if on_slot is not None:
            on_slot(slot.id)
        # the assigned stone first, then the spare ones by how well they fit the slot
        misfit = size_misfit(extents[spare], sizes[k])
        order = ([int(pick)] if pick >= 0 else []) + [spare[j] for j in np.argsort(misfit)]
        passed: list[tuple[int, str]] = []
        plan: GraspPlan | None = None
        for i in order:
            obj = db.get(objects[i].id)
            plan, targets, free, why = _plan_pick(
                project, obj, slot, map_points, ground, gripper, reachable, rng
            )
            if plan is not None and plan.chosen is not None:
                break
            passed.append((obj.id, why))
        if plan is None or plan.chosen is None:
            last, why = passed.pop() if passed else (-1, "no stone left for the slot")
            picks.append(PickResult(slot.id, last, plan, reason=why, passed_over=tuple(passed)))
            continue
        if i in spare:
            spare.remove(i)
        G = plan.grasps.T_world_gripper[plan.chosen]
        opening = float(plan.grasps.opening[plan.chosen])
        _, variant = choose_release(
            obj.T_world_object, G[None], targets, reachable, CLEARANCE, free, [opening]
        )
        T_target = targets[int(variant[0])]
        R = release_poses(obj.T_world_object, G, targets)[int(variant[0])]

        stone = int(np.argmin(np.linalg.norm(site.centers_of_mass() - obj.centroid[None], axis=1)))
        # the machine executes the grasp and the release off by its repeatability
        G_done, R_done = executed(G, sigma, rng), executed(R, sigma, rng)
        outcome = grasp_outcome(
            G_done, opening, site.stone_mesh(stone), site.scene(exclude=(stone,)), gripper
        )
        T_true = true_object_pose(obj, site.stone_mesh(stone))
        db = grasp(db, obj.id, G)
        map_points = remove_object_points(map_points, obj.centroid)
        db = release(db, obj.id, R)
        # the stone rides with the gripper as a rigid body (no settling in the slot)
        moved = R_done @ inv_T(G_done)
        site = site.moved(stone, moved @ site.T_world_stone[stone])
        error = float(np.linalg.norm((moved @ T_true)[:3, 3] - T_target[:3, 3]))
        local = cabin_swing_poses(T_world_base, rescan_yaws(spec, T_world_base, T_target[:3, 3]))
        rescan = scan_site(site, local, rng)
        map_points = lidar_map(np.vstack([map_points, rescan.points_world]), centre)
        db, rmse = realign(db, obj.id, map_points)
        picks.append(
            PickResult(
                slot.id,
                obj.id,
                plan,
                T_grasp=G,
                T_release=R,
                T_target=T_target,
                T_object=obj.T_world_object,
                opening=opening,
                passed_over=tuple(passed),
                stone=stone,
                outcome=outcome,
                placement_error=error,
                realign_rmse=rmse,
            )
        )
    return StoneRun(
        perception=perception,
        registration_success=registration_success,
        registration_error_m=reg_error,
        picks=picks,
        db=db,
        map_points=map_points,
        site=site,
        site_initial=site_initial,
        T_world_base=T_world_base,
        swing=swing,
    )
