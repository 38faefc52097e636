"""Closed-form inverse kinematics of an excavator arm with a spherical gripper wrist.

The chain of a walking excavator fitted with a rotating gripper (HEAP, paper
002): joint 1 slews the superstructure about the vertical, joints 2 (boom) and
3 (stick) pitch about parallel horizontal axes, and a wrist of three axes that
meet in one point, the wrist centre at the end of the stick, carries the
gripper: joint 4 pitches it about an axis parallel to the boom's, joint 5 tilts
it sideways, joint 6 turns it about its approach axis (the rotator). Standard
DH, all joint signs +1:

====  =====  =========  =====  ==========
link  a (m)  alpha      d (m)  offset
====  =====  =========  =====  ==========
1     a1     +90 deg    d1     0
2     a2     0          0      0
3     a3     0          0      0
4     0      -90 deg    0      0
5     0      +90 deg    0      +90 deg
6     0      0          d6     +90 deg
====  =====  =========  =====  ==========

With all joints at 0 the boom and the stick point forward (+x of the base),
level, and the gripper continues the stick. Positive boom, stick and wrist
pitch raise the part they move; the approach axis then points at the angle
``q2 + q3 + q4`` above horizontal (tilt 0). Positive tilt swings the gripper to
the left of the arm (+y of the base with the gripper pointing down in front).
The last DH frame is the flange: z the approach axis, and with the gripper
pointing down in front of the machine (slew, tilt and rotator at 0) x points
forward and y to the right, the direction in which the jaws close.

Because the wrist axes intersect, the wrist centre ``flange - d6 z`` fixes
the slew and the boom-stick pair (a planar two-link problem in the slew plane),
and the wrist angles follow from the remaining rotation ``R_03^T R``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fabflow.robots.chain import dh_table

FloatArray = NDArray[np.float64]

ALPHA_DEG = (90.0, 0.0, 0.0, -90.0, 90.0, 0.0)
"""DH twists of the excavator chain (degrees)."""

OFFSET_DEG = (0.0, 0.0, 0.0, 0.0, 90.0, 90.0)
"""DH angle offsets, ``theta = q + offset`` (degrees)."""

_SINGULAR = 1e-12
"""Below this distance (metres) or sine, an angle is left to the reference."""


@dataclass(frozen=True)
class ExcavatorParameters:
    """Lengths of the excavator chain (metres).

    Attributes
    ----------
    d1
        Height of the boom pivot above the base frame (along the slew axis).
    a1
        Horizontal offset of the boom pivot ahead of the slew axis.
    a2
        Boom: boom pivot to stick pivot.
    a3
        Stick: stick pivot to the wrist centre.
    d6
        Wrist centre to the flange, along the approach axis.
    """

    d1: float
    a1: float
    a2: float
    a3: float
    d6: float


def excavator_dh(p: ExcavatorParameters) -> FloatArray:
    """The ``(6, 4)`` DH table ``[a, alpha, d, offset]`` (metres, radians) of the chain."""
    return dh_table(
        a=[p.a1, p.a2, p.a3, 0.0, 0.0, 0.0],
        alpha_deg=ALPHA_DEG,
        d=[p.d1, 0.0, 0.0, 0.0, 0.0, p.d6],
        offset_deg=OFFSET_DEG,
    )


def _rot(theta: FloatArray, alpha_deg: float) -> FloatArray:
    """Rotation part ``Rz(theta) Rx(alpha)`` of DH link transforms, shape ``(..., 3, 3)``.

    ``alpha_deg`` is a multiple of 90 deg, so its cosine and sine are exact integers.
    """
    ct, st = np.cos(theta), np.sin(theta)
    alpha = np.radians(alpha_deg)
    ca, sa = round(np.cos(alpha)), round(np.sin(alpha))
    R = np.zeros((*np.shape(theta), 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = ct, -st * ca, st * sa
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = st, ct * ca, -ct * sa
    R[..., 2, 1], R[..., 2, 2] = sa, ca
    return R


def excavator_ik(
    p: ExcavatorParameters, T_base_flange: FloatArray, q_ref: FloatArray | None = None
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """All eight closed-form solutions for many flange poses.

    Parameters
    ----------
    p
        Chain lengths.
    T_base_flange
        ``(N, 4, 4)`` flange poses in the base frame (metres).
    q_ref
        ``(6,)`` or ``(N, 6)`` reference joints (radians); only used where the
        wrist centre lies on the slew axis (slew free) or the tilt is at
        +-90 deg (wrist pitch and rotator aligned).

    Returns
    -------
    q : numpy.ndarray
        ``(N, 8, 6)`` joint values (radians) wrapped to (-pi, pi]. Branch
        ``4 s + 2 e + w``: slew ``s`` = 0 towards the wrist centre, 1 turned
        half a turn away from it (boom over the top); elbow ``e`` = 0 with the
        stick folded down (q3 <= 0), 1 folded up; wrist ``w`` = 0 with the tilt
        within +-90 deg, 1 with the tilt beyond (wrist pitch and rotator half a
        turn round).
    exists : numpy.ndarray
        ``(N, 8)`` bool, False where the wrist centre is out of the boom and
        stick's reach for the branch.

    Notes
    -----
    At a singularity the joint a reference settles keeps its reference value
    (0 without a reference): the slew when the wrist centre is on the slew
    axis, the wrist pitch when the tilt is at +-90 deg (the rotator then takes
    the rest of the rotation). Both lie outside the catalogue arm's limits.
    """
    T = np.asarray(T_base_flange, dtype=float)
    n = T.shape[0]
    ref = (
        np.zeros((n, 6))
        if q_ref is None
        else np.broadcast_to(np.asarray(q_ref, dtype=float), (n, 6))
    )
    R = T[:, :3, :3]
    w = T[:, :3, 3] - p.d6 * R[:, :, 2]
    rxy = np.hypot(w[:, 0], w[:, 1])
    toward = np.where(rxy < _SINGULAR, ref[:, 0], np.arctan2(w[:, 1], w[:, 0]))
    h = w[:, 2] - p.d1

    q = np.zeros((n, 8, 6))
    exists = np.zeros((n, 8), dtype=bool)
    for s, q1 in enumerate((toward, toward + np.pi)):
        rho = w[:, 0] * np.cos(q1) + w[:, 1] * np.sin(q1) - p.a1
        c3 = (rho**2 + h**2 - p.a2**2 - p.a3**2) / (2.0 * p.a2 * p.a3)
        ok = np.abs(c3) <= 1.0 + 1e-12
        acos3 = np.arccos(np.clip(c3, -1.0, 1.0))
        for e, q3 in enumerate((-acos3, acos3)):
            q2 = np.arctan2(h, rho) - np.arctan2(p.a3 * np.sin(q3), p.a2 + p.a3 * np.cos(q3))
            R03 = _rot(q1, ALPHA_DEG[0]) @ _rot(q2 + q3, 0.0)
            M = np.swapaxes(R03, -1, -2) @ R
            # Approach axis in frame 3: (cos q5 cos q4, cos q5 sin q4, -sin q5).
            mx, my, mz = M[:, 0, 2], M[:, 1, 2], M[:, 2, 2]
            c5 = np.hypot(mx, my)
            for k, sign in enumerate((1.0, -1.0)):
                q4 = np.where(c5 < _SINGULAR, ref[:, 3], np.arctan2(sign * my, sign * mx))
                q5 = np.arctan2(-mz, sign * c5)
                # The rotator from the rest of the rotation, so that the three wrist
                # angles reproduce it exactly.
                R35 = _rot(q4, ALPHA_DEG[3]) @ _rot(q5 + np.radians(OFFSET_DEG[4]), ALPHA_DEG[4])
                N = np.swapaxes(R35, -1, -2) @ M
                q6 = np.arctan2(N[:, 1, 0], N[:, 0, 0]) - np.radians(OFFSET_DEG[5])
                b = 4 * s + 2 * e + k
                q[:, b] = np.stack([q1, q2, q3, q4, q5, q6], axis=1)
                exists[:, b] = ok
    q = np.pi - np.mod(np.pi - q, 2.0 * np.pi)
    return q, exists
