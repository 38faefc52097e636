"""Closed-form inverse kinematics of the Universal Robots arms (all eight branches).

The geometric solution of Hawkins (2013), "Analytic inverse kinematics for the
Universal Robots UR-5/UR-10 arms", on the standard DH table
``d = [d1, 0, 0, d4, d5, d6]``, ``a = [0, a2, a3, 0, 0, 0]``,
``alpha = [pi/2, 0, 0, pi/2, -pi/2, 0]``, vectorized over poses.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def _dh(theta: FloatArray, d: float, a: float, alpha: float) -> FloatArray:
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    T = np.zeros((*np.shape(theta), 4, 4))
    T[..., 0, 0], T[..., 0, 1], T[..., 0, 2], T[..., 0, 3] = ct, -st * ca, st * sa, a * ct
    T[..., 1, 0], T[..., 1, 1], T[..., 1, 2], T[..., 1, 3] = st, ct * ca, -ct * sa, a * st
    T[..., 2, 1], T[..., 2, 2], T[..., 2, 3] = sa, ca, d
    T[..., 3, 3] = 1.0
    return T


def _inv(T: FloatArray) -> FloatArray:
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -(Rt @ T[..., :3, 3, None])[..., 0]
    Ti[..., 3, 3] = 1.0
    return Ti


def ur_ik(
    p: Mapping[str, float], T_base_flange: FloatArray, q_ref: FloatArray | None = None
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """All eight closed-form solutions for many UR flange poses.

    Parameters
    ----------
    p
        DH lengths ``d1, a2, a3, d4, d5, d6`` (metres).
    T_base_flange
        ``(N, 4, 4)`` flange poses in the DH base frame (metres).
    q_ref
        ``(6,)`` or ``(N, 6)`` reference joints (radians); only used when joint 5
        is at 0.

    Returns
    -------
    q : numpy.ndarray
        ``(N, 8, 6)`` joint values (radians) wrapped to (-pi, pi]; branches are
        (shoulder left/right) x (wrist up/down) x (elbow up/down).
    exists : numpy.ndarray
        ``(N, 8)`` bool, False where the branch does not exist for the pose.

    Notes
    -----
    When joint 5 is at 0 (joints 4 and 6 aligned) only their sum matters;
    joint 6 then keeps its reference value (0 without a reference).
    """
    d1, a2, a3, d4, d5, d6 = (p[k] for k in ("d1", "a2", "a3", "d4", "d5", "d6"))
    T06 = np.asarray(T_base_flange, dtype=float)
    n = T06.shape[0]
    ref6 = (
        np.zeros(n)
        if q_ref is None
        else np.broadcast_to(np.asarray(q_ref, dtype=float), (n, 6))[:, 5]
    )
    p05 = T06[:, :3, 3] - d6 * T06[:, :3, 2]
    rxy = np.hypot(p05[:, 0], p05[:, 1])
    psi = np.arctan2(p05[:, 1], p05[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        arg_phi = d4 / rxy
    ok1 = np.abs(arg_phi) <= 1.0
    phi = np.arccos(np.clip(arg_phi, -1.0, 1.0))
    T60 = _inv(T06)

    q = np.zeros((n, 8, 6))
    exists = np.zeros((n, 8), dtype=bool)
    k = 0
    for s_sh in (1.0, -1.0):
        th1 = psi + s_sh * phi + np.pi / 2
        s1, c1 = np.sin(th1), np.cos(th1)
        arg5 = (T06[:, 0, 3] * s1 - T06[:, 1, 3] * c1 - d4) / d6
        ok5 = np.abs(arg5) <= 1.0 + 1e-12
        acos5 = np.arccos(np.clip(arg5, -1.0, 1.0))
        for s_wr in (1.0, -1.0):
            th5 = s_wr * acos5
            s5 = np.sin(th5)
            singular = np.abs(s5) < 1e-7
            s5_safe = np.where(singular, 1.0, s5)
            th6 = np.arctan2(
                (-T60[:, 1, 0] * s1 + T60[:, 1, 1] * c1) / s5_safe,
                (T60[:, 0, 0] * s1 - T60[:, 0, 1] * c1) / s5_safe,
            )
            th6 = np.where(singular, ref6, th6)
            # acos loses half the digits next to +-1: snap an aligned wrist to 0 / pi.
            th5 = np.where(singular, np.round(th5 / np.pi) * np.pi, th5)
            T01 = _dh(th1, d1, 0.0, np.pi / 2)
            T45 = _dh(th5, d5, 0.0, -np.pi / 2)
            T56 = _dh(th6, d6, 0.0, 0.0)
            T14 = _inv(T01) @ T06 @ _inv(T45 @ T56)
            p13 = T14[:, :3, 3] - d4 * T14[:, :3, 1]
            r13 = np.linalg.norm(p13, axis=1)
            arg3 = (r13**2 - a2**2 - a3**2) / (2.0 * a2 * a3)
            ok3 = np.abs(arg3) <= 1.0 + 1e-12
            acos3 = np.arccos(np.clip(arg3, -1.0, 1.0))
            for s_el in (1.0, -1.0):
                th3 = s_el * acos3
                with np.errstate(invalid="ignore", divide="ignore"):
                    th2 = -np.arctan2(p13[:, 1], -p13[:, 0]) + np.arcsin(
                        np.clip(a3 * np.sin(th3) / r13, -1.0, 1.0)
                    )
                T12 = _dh(th2, 0.0, a2, 0.0)
                T23 = _dh(th3, 0.0, a3, 0.0)
                T34 = _inv(T12 @ T23) @ T14
                th4 = np.arctan2(T34[:, 1, 0], T34[:, 0, 0])
                q[:, k] = np.stack([th1, th2, th3, th4, th5, th6], axis=1)
                exists[:, k] = ok1 & ok5 & ok3
                k += 1
    q = np.pi - np.mod(np.pi - q, 2.0 * np.pi)
    return q, exists
