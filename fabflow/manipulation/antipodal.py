"""The antipodal test of grasp hypotheses on a point cloud (paper 002, section 5.3).

The paper tells force-closure grasps by a CNN; :func:`force_closure` replaces it with a
geometric test on the points in each hypothesis' closing region. Points are in metres in
the world frame; ``y`` is the gripper's closing direction.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


def segment_reduce(
    ufunc: np.ufunc, values: FloatArray, keys: IntArray, n: int, empty: float
) -> FloatArray:
    """Reduce ``values`` per key (keys sorted ascending) into an ``(n,)`` array."""
    out = np.full(n, empty)
    if len(values) == 0:
        return out
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    out[keys[starts]] = ufunc.reduceat(values, starts)
    return out


def force_closure(
    points: FloatArray,
    normals: FloatArray,
    object_mask: BoolArray,
    closing: tuple[IntArray, IntArray, FloatArray],
    approach: FloatArray,
    contact_tolerance: float,
    friction_coefficient: float,
) -> tuple[BoolArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Antipodal test on the closing-region points of each hypothesis.

    The contact of a jaw is the centroid of the points within ``contact_tolerance`` (along
    ``y``) of the one nearest that jaw. A grasp passes when both contacts are mostly
    object points, they are apart, and both outward mean normals lie inside the friction
    cone about the line between the contacts.

    Parameters
    ----------
    points, normals, object_mask
        The planning cloud: ``(N, 3)`` points (world, metres), their outward unit
        normals and which of them belong to the object.
    closing
        ``(k, j, v)``: hypothesis index (sorted ascending), cloud index and ``y``
        (metres, gripper frame) of every point in a closing region, as returned by
        :func:`~fabflow.manipulation.gripper.sweep_approach`.
    approach
        ``(K, 3)`` unit approach direction of each hypothesis (world).
    contact_tolerance
        Depth of a contact patch along ``y`` (metres).
    friction_coefficient
        ``mu``; the friction cone's half-angle is ``atan(mu)``.

    Returns
    -------
    ok, contacts, v_max, v_min, reach
        ``(K,)`` verdicts, ``(K, 2, 3)`` contacts of the ``+y`` and ``-y`` jaw (world),
        the ``y`` of the extreme points and the largest ``p · approach`` of a point of
        either contact patch (world ``approach``, ``(K, 3)`` unit vectors).
    """
    k, j, v = closing
    n_hyp = len(approach)
    v_max = segment_reduce(np.maximum, v, k, n_hyp, -np.inf)
    v_min = segment_reduce(np.minimum, v, k, n_hyp, np.inf)
    contacts = np.full((n_hyp, 2, 3), np.nan)
    mean_normal = np.zeros((n_hyp, 2, 3))
    on_object = np.zeros((n_hyp, 2))
    reach = np.full(n_hyp, -np.inf)
    for side, patch in enumerate(
        (v >= v_max[k] - contact_tolerance, v <= v_min[k] + contact_tolerance)
    ):
        kp, jp = k[patch], j[patch]
        count = np.bincount(kp, minlength=n_hyp).astype(float)
        safe = np.maximum(count, 1.0)
        for axis in range(3):
            contacts[:, side, axis] = np.bincount(kp, points[jp, axis], minlength=n_hyp) / np.where(
                count > 0, safe, np.nan
            )
            mean_normal[:, side, axis] = np.bincount(kp, normals[jp, axis], minlength=n_hyp)
        on_object[:, side] = np.bincount(kp, object_mask[jp], minlength=n_hyp) / safe
        along = np.einsum("ij,ij->i", points[jp], approach[kp])
        reach = np.maximum(reach, segment_reduce(np.maximum, along, kp, n_hyp, -np.inf))
    mean_normal /= np.maximum(np.linalg.norm(mean_normal, axis=2, keepdims=True), 1e-12)
    line = contacts[:, 0] - contacts[:, 1]
    length = np.linalg.norm(line, axis=1)
    with np.errstate(invalid="ignore"):
        line = line / length[:, None]
        cos_cone = np.cos(np.arctan(friction_coefficient))
        ok = (
            (length > contact_tolerance)
            & np.all(on_object >= 0.5, axis=1)
            & (np.einsum("ij,ij->i", mean_normal[:, 0], line) >= cos_cone)
            & (np.einsum("ij,ij->i", mean_normal[:, 1], -line) >= cos_cone)
        )
    return ok, contacts, v_max, v_min, reach
