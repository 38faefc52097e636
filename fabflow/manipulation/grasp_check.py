"""The simulation's ground truth of a grasp: does a planned grasp hold the true stone?

The planner (:mod:`fabflow.manipulation.grasp`) sees a point cloud; this check sees the
true meshes. A grasp at ``T_world_gripper`` with the jaws open by ``opening`` succeeds
when all three tests pass:

(a) collision-free: the open gripper (:func:`~fabflow.manipulation.gripper.gripper_mesh`)
    at the grasp pose touches neither the obstacles (ground, other stones) nor the
    stone itself (triangle-level tests with python-fcl);
(b) antipodal: closing the jaws along ``±y`` from the opening, each jaw stops where it
    first touches the stone. Rays cast from a grid of points on each jaw's inner face
    along the closing direction find that touch: the jaw stops at the nearest hit, and
    the hits within ``contact_tolerance`` of it form the jaw's contact patch. Both jaws
    must touch within the closing region (a ray travels at most the opening), and the
    mean true face normals of both patches must lie within the friction cone
    (half-angle ``atan(mu)``) of the line between the patch centroids;
(c) held: the stone's centre of mass (``stone.center_mass``), in the gripper frame,
    lies within the jaws' width in ``x`` and between the palm (``z >= -jaw_length``) and
    the far end of the contacts (``z <=`` the largest ``z`` of a contact patch), so the
    contacts reach at least as deep as the centre of mass rather than pinching the
    stone's near end. A contact line tilted across the stone counts by its deeper end.

Everything is in metres in the world frame; the gripper frame is that of
:mod:`fabflow.manipulation.gripper` (``z`` approach, ``y`` closing, origin between the
jaws' tips).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.manipulation.gripper import TwoJawGripper, gripper_mesh

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class GraspOutcome:
    """The verdict of :func:`grasp_outcome`.

    Attributes
    ----------
    success
        All three tests passed.
    antipodal
        Both jaws touch the stone and the contacts lie in each other's friction cone.
    collision_free
        The open gripper touches neither the stone nor an obstacle.
    held
        The centre of mass lies between the palm and the contacts, within the jaws'
        width.
    contacts
        ``(2, 3)`` contact points of the ``+y`` and the ``-y`` jaw (world, metres); NaN
        for a jaw that touches nothing.
    reason
        ``"ok"``, or which test failed first and why.
    """

    success: bool
    antipodal: bool
    collision_free: bool
    held: bool
    contacts: FloatArray
    reason: str


def _collision_reason(
    T: FloatArray,
    opening: float,
    stone: trimesh.Trimesh,
    obstacles: trimesh.Trimesh | None,
    gripper: TwoJawGripper,
) -> str:
    """Empty when the open gripper is free, else what it collides with."""
    hand = gripper_mesh(gripper, opening)
    for name, mesh in (("the stone", stone), ("an obstacle", obstacles)):
        if mesh is None or len(mesh.faces) == 0:
            continue
        manager = trimesh.collision.CollisionManager()
        manager.add_object("target", mesh)
        if manager.in_collision_single(hand, transform=T):
            return f"the open gripper collides with {name}"
    return ""


def _jaw_grid(gripper: TwoJawGripper, spacing: float) -> FloatArray:
    """``(M, 2)`` points ``(x, z)`` covering a jaw's inner face, edges included."""
    nx = max(2, int(np.ceil(gripper.jaw_width / spacing)) + 1)
    nz = max(2, int(np.ceil(gripper.jaw_length / spacing)) + 1)
    gx, gz = np.meshgrid(
        np.linspace(-gripper.jaw_width / 2.0, gripper.jaw_width / 2.0, nx),
        np.linspace(-gripper.jaw_length, 0.0, nz),
    )
    return np.column_stack([gx.ravel(), gz.ravel()])


def _jaw_contact(
    T: FloatArray,
    stone: trimesh.Trimesh,
    grid: FloatArray,
    side: float,
    opening: float,
    tolerance: float,
) -> tuple[FloatArray, FloatArray, float] | None:
    """Contact patch of the jaw on side ``±1`` of ``y``: centroid, mean normal (world)
    and the largest gripper ``z`` of the patch; ``None`` when the jaw touches nothing."""
    local = np.column_stack([grid[:, 0], np.full(len(grid), side * opening / 2.0), grid[:, 1]])
    origins = local @ T[:3, :3].T + T[:3, 3]
    direction = -side * T[:3, 1]
    hits, rays, faces = stone.ray.intersects_location(
        origins, np.tile(direction, (len(origins), 1)), multiple_hits=False
    )
    if len(hits) == 0:
        return None
    dist = (hits - origins[rays]) @ direction
    inside = (dist >= -1e-9) & (dist <= opening)
    if not inside.any():
        return None
    hits, faces, dist = hits[inside], faces[inside], dist[inside]
    patch = dist <= dist.min() + tolerance
    normal = stone.face_normals[faces[patch]].sum(axis=0)
    normal /= max(np.linalg.norm(normal), 1e-12)
    reach = float(((hits[patch] - T[:3, 3]) @ T[:3, 2]).max())
    return hits[patch].mean(axis=0), normal, reach


def grasp_outcome(
    T_world_gripper: ArrayLike,
    opening: float,
    stone: trimesh.Trimesh,
    obstacles: trimesh.Trimesh | None,
    gripper: TwoJawGripper,
    friction_coefficient: float = 0.5,
    contact_tolerance: float = 0.02,
    ray_spacing: float = 0.025,
) -> GraspOutcome:
    """Whether a grasp holds the true stone (see the module docstring for the tests).

    Parameters
    ----------
    T_world_gripper
        The 4x4 gripper pose (world, metres).
    opening
        Distance between the jaws' inner faces before closing (metres).
    stone
        The stone's true mesh (world frame), closed and with outward normals.
    obstacles
        The ground and the other stones as one mesh (world frame), or ``None``.
    gripper
        The gripper's dimensions.
    friction_coefficient
        ``mu`` between jaw and stone.
    contact_tolerance
        Hits within this distance (metres, along the closing direction) of a jaw's first
        hit belong to its contact patch: the give of jaw pads and stone surface, so a jaw
        tilted by a degree against a flat face still bears on the whole face.
    ray_spacing
        Spacing of the ray grid on each jaw's inner face (metres).

    Returns
    -------
    GraspOutcome
        The three verdicts, the contacts and the first failure in ``reason``.

    Raises
    ------
    InputError
        For a malformed pose, an opening outside the gripper's range or a non-positive
        friction coefficient, contact tolerance or ray spacing.
    """
    T = np.asarray(T_world_gripper, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"T_world_gripper must be a finite 4x4 matrix, got shape {T.shape}")
    w = gripper.check_opening(opening)
    for name, value in (
        ("friction_coefficient", friction_coefficient),
        ("contact_tolerance", contact_tolerance),
        ("ray_spacing", ray_spacing),
    ):
        if not value > 0:
            raise InputError(f"{name} must be positive, got {value}")
    collision = _collision_reason(T, w, stone, obstacles, gripper)
    grid = _jaw_grid(gripper, ray_spacing)
    found = [_jaw_contact(T, stone, grid, side, w, contact_tolerance) for side in (1.0, -1.0)]
    contacts = np.array([np.full(3, np.nan) if f is None else f[0] for f in found])
    antipodal, held, grip = False, False, ""
    if found[0] is None or found[1] is None:
        side = "+y" if found[0] is None else "-y"
        grip = f"the {side} jaw closes without touching the stone"
    else:
        antipodal, grip = _antipodal(found[0], found[1], friction_coefficient)
        held, hold = _held(T, stone, gripper, max(found[0][2], found[1][2]))
        grip = grip or hold
    reason = collision or grip or "ok"
    success = not collision and antipodal and held
    return GraspOutcome(success, antipodal, not collision, held, contacts, reason)


def _antipodal(
    pos: tuple[FloatArray, FloatArray, float],
    neg: tuple[FloatArray, FloatArray, float],
    friction_coefficient: float,
) -> tuple[bool, str]:
    """Both contact normals inside the friction cone about the contact line."""
    line = pos[0] - neg[0]
    length = np.linalg.norm(line)
    if length < 1e-9:
        return False, "both jaws touch the stone at the same point"
    line /= length
    cone = np.degrees(np.arctan(friction_coefficient))
    for name, normal, along in (("+y", pos[1], line), ("-y", neg[1], -line)):
        angle = np.degrees(np.arccos(np.clip(normal @ along, -1.0, 1.0)))
        if angle > cone:
            return False, (
                f"not antipodal: the stone's normal at the {name} contact is {angle:.1f}° "
                f"off the contact line (friction cone {cone:.1f}°)"
            )
    return True, ""


def _held(
    T: FloatArray, stone: trimesh.Trimesh, gripper: TwoJawGripper, reach: float
) -> tuple[bool, str]:
    """The centre of mass between palm and contacts, within the jaws' width."""
    com = (np.asarray(stone.center_mass, dtype=float) - T[:3, 3]) @ T[:3, :3]
    if abs(com[0]) > gripper.jaw_width / 2.0:
        return False, (
            f"not held: the centre of mass is {abs(com[0]):.3f} m off the jaws' middle "
            f"across their width ({gripper.jaw_width / 2.0:.3f} m allowed)"
        )
    if com[2] < -gripper.jaw_length:
        return False, "not held: the centre of mass lies behind the palm"
    if com[2] > reach:
        return False, (
            f"not held: the contacts reach {com[2] - reach:.3f} m short of the centre of mass "
            "along the approach (a pinch at the stone's near end)"
        )
    return True, ""
