"""Closed-form inverse kinematics of 6-axis arms with an ortho-parallel base and a spherical wrist.

The parametrization of Brandstötter, Angerer and Hofbaur (2014), "An analytical
solution of the inverse kinematics problem of industrial serial manipulators
with an ortho-parallel basis and a spherical wrist": seven lengths ``a1, a2, b,
c1, c2, c3, c4`` describe KUKA, ABB, Fanuc, Stäubli ... arms. In the OPW zero
pose the lower and upper arms point straight up; the controller joints relate
to the OPW angles by ``q_opw = sign * q - offset``.

The solver returns the eight branches (front/back x elbow up/down x wrist flip)
for many poses at once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class OPWParameters:
    """Geometry of an ortho-parallel arm with a spherical wrist (metres, radians).

    Attributes
    ----------
    a1
        Offset of axis 2 from axis 1, along x.
    a2
        Offset of the forearm (axis 4) from the elbow, perpendicular to the forearm.
    b
        Lateral offset of the arm plane (y).
    c1
        Height of axis 2 above the base.
    c2
        Upper arm length (axis 2 to axis 3).
    c3
        Forearm length (axis 3 to the wrist centre).
    c4
        Wrist centre to flange.
    offsets
        ``(6,)`` joint offsets, ``q_opw = sign * q - offset``.
    signs
        ``(6,)`` joint signs.
    """

    a1: float
    a2: float
    b: float
    c1: float
    c2: float
    c3: float
    c4: float
    offsets: tuple[float, ...]
    signs: tuple[float, ...]


def opw_fk(p: OPWParameters, q: FloatArray) -> FloatArray:
    """Flange pose from controller joints with the OPW formulas (cross-check of the DH chain).

    Parameters
    ----------
    p
        OPW geometry.
    q
        ``(N, 6)`` controller joint values (radians).

    Returns
    -------
    numpy.ndarray
        ``(N, 4, 4)`` flange poses in the base frame.
    """
    qq = np.asarray(q, dtype=float) * np.asarray(p.signs) - np.asarray(p.offsets)
    q1, q2, q3, q4, q5, q6 = qq.T
    psi3 = np.arctan2(p.a2, p.c3)
    k = np.hypot(p.a2, p.c3)
    cx1 = p.c2 * np.sin(q2) + k * np.sin(q2 + q3 + psi3) + p.a1
    cy1 = p.b
    cz1 = p.c2 * np.cos(q2) + k * np.cos(q2 + q3 + psi3)
    c = np.stack(
        [cx1 * np.cos(q1) - cy1 * np.sin(q1), cx1 * np.sin(q1) + cy1 * np.cos(q1), cz1 + p.c1],
        axis=-1,
    )
    R0c = _rz(q1) @ _ry(q2 + q3)
    Rce = _rz(q4) @ _ry(q5) @ _rz(q6)
    R = R0c @ Rce
    T = np.zeros((qq.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = c + p.c4 * R[:, :, 2]
    T[:, 3, 3] = 1.0
    return T


def _rz(t: FloatArray) -> FloatArray:
    c, s = np.cos(t), np.sin(t)
    R = np.zeros((*np.shape(t), 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def _ry(t: FloatArray) -> FloatArray:
    c, s = np.cos(t), np.sin(t)
    R = np.zeros((*np.shape(t), 3, 3))
    R[..., 0, 0], R[..., 0, 2], R[..., 2, 0], R[..., 2, 2], R[..., 1, 1] = c, s, -s, c, 1.0
    return R


def solved_branches(arms: Sequence[int]) -> NDArray[np.intp]:
    """The branches (0-7) :func:`opw_ik` solves when asked for ``arms`` (0-3): each arm
    branch and its wrist flip, in ascending order of the arms."""
    arm = np.unique(np.asarray(arms, dtype=np.intp))
    return np.r_[arm, arm + 4]


def opw_ik(
    p: OPWParameters,
    T_base_flange: FloatArray,
    q_ref: FloatArray | None = None,
    arms: Sequence[int] | None = None,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """All eight closed-form solutions for many flange poses.

    Parameters
    ----------
    p
        OPW geometry.
    T_base_flange
        ``(N, 4, 4)`` flange poses in the base frame (metres).
    q_ref
        ``(6,)`` or ``(N, 6)`` reference (controller joints, radians); only used at
        a wrist singularity.
    arms
        Solve only these arm branches (0-3: front/back, elbow a/b) and their
        wrist flips (4-7); the others come back NaN and not existing. Default all.

    Returns
    -------
    q : numpy.ndarray
        ``(N, 8, 6)`` controller joint values (radians), wrapped to (-pi, pi];
        branch order: (front, elbow a, wrist), (front, elbow b, wrist),
        (back, ...), (back, ...), then the same four with the wrist flipped.
    exists : numpy.ndarray
        ``(N, 8)`` bool, False where the wrist centre is out of reach for the branch.

    Notes
    -----
    At a wrist singularity (axis 5 at 0) only the sum of axes 4 and 6 is
    determined; axis 4 then keeps its reference value (0 without a reference).
    """
    T = np.asarray(T_base_flange, dtype=float)
    R = T[:, :3, :3]
    e = R[:, :, 2]
    c = T[:, :3, 3] - p.c4 * e
    cx, cy, cz = c[:, 0], c[:, 1], c[:, 2]

    with np.errstate(invalid="ignore"):
        nx1 = np.sqrt(np.maximum(cx**2 + cy**2 - p.b**2, 0.0)) - p.a1
        tmp1 = np.arctan2(cy, cx)
        tmp2 = np.arctan2(p.b, nx1 + p.a1)
        th1_i = tmp1 - tmp2
        th1_ii = tmp1 + tmp2 - np.pi

        tmp3 = cz - p.c1
        s1_2 = nx1**2 + tmp3**2
        tmp4 = nx1 + 2.0 * p.a1
        s2_2 = tmp4**2 + tmp3**2
        kappa_2 = p.a2**2 + p.c3**2
        c2_2 = p.c2**2
        s1 = np.sqrt(s1_2)
        s2 = np.sqrt(s2_2)

        arg13 = (s1_2 + c2_2 - kappa_2) / (2.0 * s1 * p.c2)
        arg15 = (s2_2 + c2_2 - kappa_2) / (2.0 * s2 * p.c2)
        tmp9 = 2.0 * p.c2 * np.sqrt(kappa_2)
        arg11 = (s1_2 - c2_2 - kappa_2) / tmp9
        arg12 = (s2_2 - c2_2 - kappa_2) / tmp9
        ok_front = (np.abs(arg13) <= 1.0 + 1e-12) & (np.abs(arg11) <= 1.0 + 1e-12)
        ok_back = (np.abs(arg15) <= 1.0 + 1e-12) & (np.abs(arg12) <= 1.0 + 1e-12)
        tmp13 = np.arccos(np.clip(arg13, -1.0, 1.0))
        tmp15 = np.arccos(np.clip(arg15, -1.0, 1.0))
        tmp11 = np.arccos(np.clip(arg11, -1.0, 1.0))
        tmp12 = np.arccos(np.clip(arg12, -1.0, 1.0))
    tmp14 = np.arctan2(nx1, cz - p.c1)
    tmp16 = np.arctan2(nx1 + 2.0 * p.a1, cz - p.c1)
    tmp10 = np.arctan2(p.a2, p.c3)

    th1 = np.stack([th1_i, th1_i, th1_ii, th1_ii], axis=1)
    th2 = np.stack([-tmp13 + tmp14, tmp13 + tmp14, -tmp15 - tmp16, tmp15 - tmp16], axis=1)
    th3 = np.stack([tmp11 - tmp10, -tmp11 - tmp10, tmp12 - tmp10, -tmp12 - tmp10], axis=1)
    exists4 = np.stack([ok_front, ok_front, ok_back, ok_back], axis=1)
    if arms is not None:  # the wrist below is most of the work: only for these
        solved = solved_branches(arms)
        arm = solved[: len(solved) // 2]
        th1, th2, th3, exists4 = th1[:, arm], th2[:, arm], th3[:, arm], exists4[:, arm]

    # Wrist: R_c_e = Rz(q4) Ry(q5) Rz(q6). q5 from the norm of the third column
    # (no cancellation near q5 = 0), q4 from its direction, and q6 from the rest of
    # the rotation given q4 and q5, so the three always reproduce R_c_e exactly
    # even where q4 alone is ill-conditioned.
    R0c = _rz(th1) @ _ry(th2 + th3)
    Rce = np.swapaxes(R0c, -1, -2) @ R[:, None]
    s5 = np.hypot(Rce[..., 0, 2], Rce[..., 1, 2])
    th5 = np.arctan2(s5, Rce[..., 2, 2])
    th4 = np.arctan2(Rce[..., 1, 2], Rce[..., 0, 2])
    singular = s5 < 1e-12
    if np.any(singular):
        # Axes 4 and 6 coincide: axis 4 keeps its reference, axis 6 takes the rest.
        if q_ref is None:
            q4_ref = np.zeros((T.shape[0], 1))
        else:
            ref = np.broadcast_to(np.asarray(q_ref, dtype=float), (T.shape[0], 6))
            q4_ref = (ref[:, 3] * p.signs[3] - p.offsets[3])[:, None]
        th4 = np.where(singular, q4_ref, th4)
    M = np.swapaxes(_rz(th4) @ _ry(th5), -1, -2) @ Rce
    th6 = np.arctan2(M[..., 1, 0], M[..., 0, 0])

    k = th1.shape[1]
    q = np.empty((T.shape[0], 2 * k, 6))  # the branches solved, then their wrist flips
    q[:, :k, 0], q[:, :k, 1], q[:, :k, 2] = th1, th2, th3
    q[:, :k, 3], q[:, :k, 4], q[:, :k, 5] = th4, th5, th6
    q[:, k:, :3] = q[:, :k, :3]
    q[:, k:, 3] = th4 + np.pi
    q[:, k:, 4] = -th5
    q[:, k:, 5] = th6 - np.pi
    # in place: the same arithmetic as (q + offsets) * signs, then pi - mod(pi - q, 2 pi),
    # without three more arrays of 48 values per pose
    q += np.asarray(p.offsets)
    q *= np.asarray(p.signs)
    np.subtract(np.pi, q, out=q)
    np.mod(q, 2.0 * np.pi, out=q)
    np.subtract(np.pi, q, out=q)
    exists = np.concatenate([exists4, exists4], axis=1)
    if arms is not None:  # in the branch order of all eight
        q_all = np.full((T.shape[0], 8, 6), np.nan)
        q_all[:, solved] = q
        exists_all = np.zeros((T.shape[0], 8), dtype=bool)
        exists_all[:, solved] = exists
        q, exists = q_all, exists_all
    return q, exists
