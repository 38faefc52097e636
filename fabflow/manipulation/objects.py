"""The object database: found objects, their model points and where they have been
(paper 002, section 4.5).

Each object holds its model points in its own frame and the history of its pose
in the world: ``detected`` (segmented from the map or re-aligned to it after a
move), ``grasp`` (the gripper's world pose when the jaws closed) and ``release``
(the gripper's world pose when they opened). A release moves the object by
eq. 3 of the paper, ``T = T_release * T_grasp^-1``: the object rides with the
gripper, so its new pose is ``T * T_world_object``.

The object frame: origin at the centroid of the model points (or of the solid
they bound down to the ground, :func:`solid_centroid`), axes along their
principal directions, x the longest and z the shortest, signed so that z points
up and x towards +x of the world when detected (the pose nearest the stone's
lie). Plain data: every update returns a new database.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import ConvexHull, QhullError

from fabflow.errors import InputError
from fabflow.positioning.icp import icp, prepare_target
from fabflow.positioning.pointcloud import as_points, voxel_downsample
from fabflow.transforms.se3 import apply_T, inv_T

FloatArray = NDArray[np.float64]

EventKind = Literal["detected", "grasp", "release"]

R_OBJECT = 1.0
"""``R_obj`` (Table 3): radius around a grasped object's centroid whose map points
are removed (metres)."""
MAX_RMSE = 0.03
"""``e*_icp`` (Table 3): largest ICP RMSE of an accepted registration (metres)."""
D_MATCH = 1.0
"""``d_match`` (Table 3): largest distance between matched segment centroids (metres)."""


@dataclass(frozen=True, eq=False)
class ObjectEvent:
    """One entry of an object's history.

    Attributes
    ----------
    event
        ``"detected"``, ``"grasp"`` or ``"release"``.
    T_world_object
        4x4 pose of the object frame in the world after the event (metres).
    T_world_gripper
        4x4 gripper pose of a grasp or release (metres), ``None`` for a detection.
    rmse
        ICP RMSE of a re-detection against the map (metres), ``None`` otherwise.
    """

    event: EventKind
    T_world_object: FloatArray
    T_world_gripper: FloatArray | None = None
    rmse: float | None = None


@dataclass(frozen=True, eq=False)
class FoundObject:
    """An object of the database.

    Attributes
    ----------
    id
        Identification number ``i`` (unique in the database).
    points
        ``(N, 3)`` model points in the object frame (metres).
    history
        Every event, oldest first; the last one holds the current pose.
    floor
        ``(M, 3)`` the model points projected onto the ground it rested on when
        detected, object frame (metres): the underside no scan sees, closed
        down to the ground (empty when the ground was not known).
    """

    id: int
    points: FloatArray
    history: tuple[ObjectEvent, ...]
    floor: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def T_world_object(self) -> FloatArray:
        """The current 4x4 pose of the object in the world (metres)."""
        return self.history[-1].T_world_object

    @property
    def centroid(self) -> FloatArray:
        """The current centroid ``c_i`` in the world (metres)."""
        return self.T_world_object[:3, 3].copy()

    def solid_points(self) -> FloatArray:
        """The model points and the floor points, object frame (metres)."""
        return np.vstack([self.points, self.floor])

    @property
    def extents(self) -> FloatArray:
        """Size of the solid along the object's x, y, z (metres; model and floor)."""
        return np.ptp(self.solid_points(), axis=0)

    @property
    def held(self) -> bool:
        """Whether the last event was a grasp (the object is in the gripper)."""
        return self.history[-1].event == "grasp"

    def world_points(self) -> FloatArray:
        """The model points at the current pose, world frame (metres)."""
        return apply_T(self.T_world_object, self.points)

    def with_event(self, event: ObjectEvent) -> FoundObject:
        """This object with one more event."""
        return replace(self, history=(*self.history, event))


def object_frame(points_world: ArrayLike) -> FloatArray:
    """The object frame of points: centroid and principal axes (module docstring).

    Parameters
    ----------
    points_world
        ``(N, 3)`` points of one object, world frame (metres), at least 4.

    Returns
    -------
    numpy.ndarray
        ``T_world_object`` (4x4): x the longest principal axis, z the shortest,
        z up and x towards world +x; right-handed.
    """
    p = as_points(points_world, "object points")
    if len(p) < 4:
        raise InputError(f"an object needs at least 4 points, got {len(p)}")
    c = p.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov((p - c).T))
    x, z = vecs[:, 2], vecs[:, 0]
    z = z if z[2] >= 0 else -z
    x = x if x[0] >= 0 else -x
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = x, np.cross(z, x), z
    T[:3, 3] = c
    return T


def solid_centroid(points_world: ArrayLike, ground_plane: ArrayLike) -> FloatArray:
    """Centroid of the solid an object's points bound, filled down to the ground.

    The convex hull of the points and of their projections onto the ground plane
    (the object rests on the ground; its underside is never seen); the centroid
    of its volume (metres, world). A scan sees an object from some sides only,
    so the average of its points lies towards the seen sides: on the simulated
    stones of ``projects/stone_wall`` by up to 0.2 m horizontally, where this
    centroid lies within a few centimetres of the true centre of mass.

    Parameters
    ----------
    points_world
        ``(N, 3)`` object points (metres, world).
    ground_plane
        ``(4,)`` plane ``(n, d)``, ``n . p + d = 0``, ``n`` a unit normal pointing up.
    """
    p = as_points(points_world, "object points")
    plane = np.asarray(ground_plane, dtype=float)
    n, d = plane[:3], plane[3]
    feet = p - np.outer(p @ n + d, n)
    try:
        hull = ConvexHull(np.vstack([p, feet]))
    except (QhullError, ValueError):
        return p.mean(axis=0)
    tri = hull.points[hull.simplices]  # (F, 3, 3)
    inner = hull.points[hull.vertices].mean(axis=0)
    volume = np.abs(np.linalg.det(tri - inner)) / 6.0
    centres = (tri.sum(axis=1) + inner) / 4.0
    return (volume @ centres) / volume.sum()


def new_object(
    object_id: int,
    points_world: ArrayLike,
    voxel_size: float = 0.03,
    ground_plane: ArrayLike | None = None,
) -> FoundObject:
    """A newly detected object from its points in the world.

    Parameters
    ----------
    object_id
        Its identification number.
    points_world
        ``(N, 3)`` segment points, world frame (metres).
    voxel_size
        Grid the model points are thinned to (metres; ``res_voxel`` of Table 3).
    ground_plane
        The ground it rests on, ``(n, d)`` with ``n`` up: the frame's origin is
        then its :func:`solid_centroid`, else the average of its points.
    """
    p, _ = voxel_downsample(as_points(points_world, "object points"), voxel_size)
    T = object_frame(p)
    floor = np.zeros((0, 3))
    if ground_plane is not None:
        T[:3, 3] = solid_centroid(p, ground_plane)
        plane = np.asarray(ground_plane, dtype=float)
        feet = p - np.outer(p @ plane[:3] + plane[3], plane[:3])
        floor = apply_T(inv_T(T), voxel_downsample(feet, voxel_size)[0])
    return FoundObject(object_id, apply_T(inv_T(T), p), (ObjectEvent("detected", T),), floor)


@dataclass(frozen=True, eq=False)
class ObjectDatabase:
    """The objects found so far, by id."""

    objects: tuple[FoundObject, ...] = ()

    def __len__(self) -> int:
        return len(self.objects)

    def get(self, object_id: int) -> FoundObject:
        """The object with this id (:class:`InputError` when there is none)."""
        for obj in self.objects:
            if obj.id == object_id:
                return obj
        raise InputError(f"no object {object_id} in the object database")

    def updated(self, obj: FoundObject) -> ObjectDatabase:
        """The database with ``obj`` replacing the object of its id (or added)."""
        rest = tuple(o for o in self.objects if o.id != obj.id)
        return ObjectDatabase(tuple(sorted((*rest, obj), key=lambda o: o.id)))

    def centroids(self) -> FloatArray:
        """``(K, 3)`` current centroids (metres, world)."""
        return np.array([o.centroid for o in self.objects]).reshape(-1, 3)


def add_segments(
    db: ObjectDatabase,
    segments: Sequence[ArrayLike],
    voxel_size: float = 0.03,
    ground_plane: ArrayLike | None = None,
) -> ObjectDatabase:
    """Add each segment's points as a new object (ids continue after the largest).

    Parameters
    ----------
    db
        The database.
    segments
        Point sets of the segments, world frame (metres).
    voxel_size
        Grid the model points are thinned to (metres).
    ground_plane
        The ground the objects rest on (see :func:`new_object`), or ``None``.
    """
    start = max((o.id for o in db.objects), default=-1) + 1
    for k, seg in enumerate(segments):
        db = db.updated(new_object(start + k, seg, voxel_size, ground_plane))
    return db


def grasp(db: ObjectDatabase, object_id: int, T_world_gripper: ArrayLike) -> ObjectDatabase:
    """Record a grasp: the gripper's world pose ``T_MG^grasp`` when the jaws closed."""
    obj = db.get(object_id)
    if obj.held:
        raise InputError(f"object {object_id} is already held")
    T = _pose(T_world_gripper, "T_world_gripper")
    return db.updated(obj.with_event(ObjectEvent("grasp", obj.T_world_object, T)))


def release(db: ObjectDatabase, object_id: int, T_world_gripper: ArrayLike) -> ObjectDatabase:
    """Record a release and move the object by eq. 3: ``T = T_release * T_grasp^-1``.

    Raises
    ------
    InputError
        The object is not held (no grasp since its last release or detection).
    """
    obj = db.get(object_id)
    if not obj.held:
        raise InputError(f"object {object_id} is released but was not grasped")
    T_grasp = obj.history[-1].T_world_gripper
    assert T_grasp is not None
    T_release = _pose(T_world_gripper, "T_world_gripper")
    moved = T_release @ inv_T(T_grasp) @ obj.T_world_object
    return db.updated(obj.with_event(ObjectEvent("release", moved, T_release)))


def realign(
    db: ObjectDatabase,
    object_id: int,
    map_points: ArrayLike,
    radius: float = R_OBJECT,
    max_rmse: float = MAX_RMSE,
) -> tuple[ObjectDatabase, float]:
    """Re-align an object's model with the map after it was remapped (ICP).

    The map points within ``radius`` of the object's centroid are the target;
    the model at its current pose the source. An alignment with an RMSE above
    ``max_rmse`` is refused and the pose kept.

    Returns
    -------
    db : ObjectDatabase
        With a ``detected`` event at the re-aligned pose (or unchanged).
    rmse : float
        The ICP RMSE (metres); ``inf`` when the map holds too few points near it.
    """
    obj = db.get(object_id)
    pts = as_points(map_points, "map points")
    near = pts[np.linalg.norm(pts - obj.centroid, axis=1) <= radius]
    if len(near) < 10:
        return db, float("inf")
    res = icp(
        obj.world_points(),
        prepare_target(near),
        max_correspondence_distance=(0.15, 0.05),
        kernel="huber",
    )
    if not res.inlier_rmse <= max_rmse:
        return db, float(res.inlier_rmse)
    T = res.T @ obj.T_world_object
    event = ObjectEvent("detected", T, rmse=float(res.inlier_rmse))
    return db.updated(obj.with_event(event)), float(res.inlier_rmse)


def remove_object_points(
    map_points: ArrayLike, centroid: ArrayLike, radius: float = R_OBJECT
) -> FloatArray:
    """The map without its points within ``radius`` of ``centroid`` (a grasped object's)."""
    pts = as_points(map_points, "map points")
    return pts[np.linalg.norm(pts - np.asarray(centroid, dtype=float), axis=1) > radius]


def _pose(T: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(T, dtype=float)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise InputError(f"{name} must be a finite 4x4 matrix")
    return a


def history_json(obj: FoundObject) -> list[dict[str, Any]]:
    """An object's history as JSON-able rows ``{event, T_world_object, T_world_gripper}``."""
    rows = []
    for e in obj.history:
        row: dict[str, Any] = {
            "event": e.event,
            "T_world_object": np.round(e.T_world_object, 9).tolist(),
            "T_world_gripper": None
            if e.T_world_gripper is None
            else np.round(e.T_world_gripper, 9).tolist(),
        }
        if e.rmse is not None:
            row["rmse_m"] = round(e.rmse, 6)
        rows.append(row)
    return rows
