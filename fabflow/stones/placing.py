"""Which stone goes in which slot, how it sits there, and the gripper's release pose.

A slot asks for a size (length along the wall, width, height); a stone offers
the extents of its model along its principal axes. The assignment matches
sorted extents to sorted slot sizes (the smallest total difference over all
slots, :func:`scipy.optimize.linear_sum_assignment`). In its slot a stone lies
with its longest axis along the wall and its shortest up, its centroid over the
slot's centre and the lowest point of its solid (the model closed down to the
ground it lay on, :attr:`~fabflow.manipulation.objects.FoundObject.floor`) on
the slot's floor; turned by a half
turn about any of its axes it fits as well, so four orientations are offered
and the one the machine reaches with the gripper nearest to vertical is taken.

The release must be free: the open gripper there clear of the map (the
neighbours set before, the ground). The gripper holds the stone rigidly, so
the release pose follows from the grasp:
``T_release = T_world_object_target * T_world_object^-1 * T_grasp``, the inverse
of eq. 3 of paper 002.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment
from scipy.spatial import ConvexHull, QhullError

from fabflow.errors import InputError
from fabflow.manipulation.objects import FoundObject
from fabflow.transforms.se3 import inv_T

FloatArray = NDArray[np.float64]

STONE_DENSITY = 2700.0
"""Density of the stones (kg/m^3): gneiss, the rock of paper 002's experiments."""


def stone_mass(obj: FoundObject, density: float = STONE_DENSITY) -> float:
    """Mass estimate of an object: the volume of its model's convex hull times ``density`` (kg).

    The hull over-estimates a dented stone's volume: the load data err on the
    heavy side.
    """
    try:
        return float(ConvexHull(obj.points).volume) * density
    except (QhullError, ValueError):
        return 0.0


HALF_TURNS = np.stack(
    [
        np.diag([1.0, 1.0, 1.0, 1.0]),
        np.diag([-1.0, -1.0, 1.0, 1.0]),
        np.diag([1.0, -1.0, -1.0, 1.0]),
        np.diag([-1.0, 1.0, -1.0, 1.0]),
    ]
)
"""The identity and the half turns about the object's z, x and y axes (4x4)."""


def size_misfit(extents: ArrayLike, size: ArrayLike) -> FloatArray:
    """How badly objects fit a slot: the distance between their extents and the slot's
    size, both sorted largest first (metres; broadcasts over leading axes).

    Parameters
    ----------
    extents
        ``(..., 3)`` objects' extents (metres).
    size
        ``(..., 3)`` slot length, width and height (metres).
    """
    e = -np.sort(-np.asarray(extents, dtype=float), axis=-1)
    s = -np.sort(-np.asarray(size, dtype=float), axis=-1)
    return np.linalg.norm(e - s, axis=-1)


def assign_slots(extents: ArrayLike, slot_sizes: ArrayLike) -> NDArray[np.intp]:
    """The object for each slot: sorted extents matched to sorted slot sizes.

    Parameters
    ----------
    extents
        ``(K, 3)`` objects' extents (metres).
    slot_sizes
        ``(S, 3)`` slots' sizes (metres).

    Returns
    -------
    numpy.ndarray
        ``(S,)`` object index per slot; ``-1`` where there are fewer objects than
        slots (the slots whose best match is worst go empty).
    """
    s = np.asarray(slot_sizes, dtype=float).reshape(-1, 3)
    e = np.asarray(extents, dtype=float).reshape(-1, 3)
    out = np.full(len(s), -1, dtype=np.intp)
    if len(e) == 0:
        return out
    cost = size_misfit(e[None, :, :], s[:, None, :])
    rows, cols = linear_sum_assignment(cost)
    out[rows] = cols
    return out


def target_poses(obj: FoundObject, T_world_slot: ArrayLike, size: ArrayLike) -> FloatArray:
    """The object's four fitting poses in a slot (module docstring).

    Parameters
    ----------
    obj
        The object (its model points in its own frame).
    T_world_slot
        4x4 slot pose: centre of the slot box, x along the wall, z up (metres).
    size
        ``(3,)`` slot length, width, height (metres).

    Returns
    -------
    numpy.ndarray
        ``(4, 4, 4)`` ``T_world_object`` targets.
    """
    T_slot = np.asarray(T_world_slot, dtype=float)
    height = float(np.asarray(size, dtype=float)[2])
    solid = obj.solid_points()
    lowest = np.einsum("vij,nj->vni", HALF_TURNS[:, :3, :3], solid)[..., 2].min(axis=1)
    T_slot_object = HALF_TURNS.copy()
    T_slot_object[:, 2, 3] = -0.5 * height - lowest
    return T_slot @ T_slot_object


def release_poses(
    T_world_object: ArrayLike, T_world_grasp: ArrayLike, targets: ArrayLike
) -> FloatArray:
    """Gripper poses that set the held object at each target (inverse of eq. 3).

    Parameters
    ----------
    T_world_object
        4x4 the object's pose when grasped.
    T_world_grasp
        ``(4, 4)`` or ``(M, 4, 4)`` gripper poses of the grasp.
    targets
        ``(V, 4, 4)`` the object's target poses.

    Returns
    -------
    numpy.ndarray
        ``(M, V, 4, 4)`` (or ``(V, 4, 4)`` for one grasp) release poses.
    """
    G = np.asarray(T_world_grasp, dtype=float)
    single = G.ndim == 2
    G = G.reshape(-1, 4, 4)
    held = inv_T(np.asarray(T_world_object, dtype=float)) @ G
    out = np.einsum("vij,mjk->mvik", np.asarray(targets, dtype=float), held)
    return out[0] if single else out


def backed_off(T_world_gripper: ArrayLike, distance: float) -> FloatArray:
    """Gripper poses moved back along their approach (gripper -z) by ``distance`` (m)."""
    T = np.array(T_world_gripper, dtype=float)
    T[..., :3, 3] -= distance * T[..., :3, 2]
    return T


def raised(T: ArrayLike, height: float) -> FloatArray:
    """Poses moved straight up by ``height`` (metres, world z)."""
    out = np.array(T, dtype=float)
    out[..., 2, 3] += height
    return out


def choose_release(
    T_world_object: ArrayLike,
    T_world_grasp: ArrayLike,
    targets: ArrayLike,
    reachable: Callable[[FloatArray], NDArray[np.bool_]],
    clearance: float,
    free: Callable[[FloatArray, FloatArray], NDArray[np.bool_]] | None = None,
    openings: ArrayLike | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.intp]]:
    """For each grasp, whether a target can be reached and which (the most vertical).

    The machine must reach the grasp, its approach (``clearance`` back along
    the gripper's z) and its lift (``clearance`` straight up), and for some
    target the release, its approach from straight above and its retreat back
    along the gripper's z.

    Parameters
    ----------
    T_world_object
        4x4 the object's pose.
    T_world_grasp
        ``(M, 4, 4)`` candidate grasps.
    targets
        ``(V, 4, 4)`` the object's target poses.
    reachable
        Maps ``(K, 4, 4)`` gripper poses (world) to ``(K,)`` bool: the machine
        reaches them.
    clearance
        Approach, lift and retreat distance (metres).
    free
        Maps ``(K, 4, 4)`` release poses and ``(K,)`` jaw openings to ``(K,)`` bool:
        the gripper there is clear of the map (neighbours, ground); ``None``: not
        checked.
    openings
        ``(M,)`` the grasps' jaw openings (metres), for ``free``.

    Returns
    -------
    ok : numpy.ndarray
        ``(M,)`` bool: the grasp with its approach and lift, and a release with
        its approach and retreat, are all reachable (and the release is free).
    variant : numpy.ndarray
        ``(M,)`` index of the chosen target (the release whose approach points
        most nearly straight down), ``-1`` where none is reachable.
    """
    G = np.asarray(T_world_grasp, dtype=float).reshape(-1, 4, 4)
    if len(G) == 0:
        return np.zeros(0, dtype=bool), np.zeros(0, dtype=np.intp)
    R = release_poses(T_world_object, G, targets)
    m, v = R.shape[:2]
    flat = R.reshape(-1, 4, 4)
    poses = np.concatenate(
        [
            G,
            backed_off(G, clearance),
            raised(G, clearance),
            flat,
            raised(flat, clearance),
            backed_off(flat, clearance),
        ]
    )
    ok = np.asarray(reachable(poses), dtype=bool)
    if ok.shape != (len(poses),):
        raise InputError("the reach check must return one bool per pose")
    grasp_ok = ok[:m] & ok[m : 2 * m] & ok[2 * m : 3 * m]
    at = ok[3 * m :].reshape(3, m * v)
    release_ok = (at[0] & at[1] & at[2]).reshape(m, v)
    if free is not None:
        # only the reachable releases of reachable grasps are checked for collisions
        widths = np.repeat(np.asarray(openings, dtype=float).reshape(m), v)
        todo = np.flatnonzero((release_ok & grasp_ok[:, None]).ravel())
        clear = np.zeros(m * v, dtype=bool)
        if len(todo):
            found = np.asarray(free(flat[todo], widths[todo]), dtype=bool)
            if found.shape != (len(todo),):
                raise InputError("the collision check must return one bool per pose")
            clear[todo] = found
        release_ok &= clear.reshape(m, v)
    down = -R[:, :, 2, 2]  # the approach's downward component
    score = np.where(release_ok, down, -np.inf)
    variant = np.where(release_ok.any(axis=1), np.argmax(score, axis=1), -1)
    return grasp_ok & release_ok.any(axis=1), variant.astype(np.intp)
