"""Three-point localization (paper 001, eqs 1-6): base pose from ``P1``, ``P1 + d x``, ``P1 + d y``.

The prism is moved to three points of the base frame a step ``d`` apart along
its x and y axes; the measured points give the base axes directly.
:func:`localize_three_point` adds the first-order covariance.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fabflow.errors import InputError
from fabflow.positioning.adjustment_tests import ALPHA
from fabflow.positioning.integrity import record, unchecked
from fabflow.positioning.registration import Registration, point_tests
from fabflow.positioning.rigid_fit import as_points, check_geometry, refine_registration
from fabflow.transforms.se3 import make_T
from fabflow.transforms.so3 import log_so3


def three_point_base_points(p1: Any, d: float) -> np.ndarray:
    """The localization points of eqs 1-6 in the base frame: ``P1``, ``P1 + d x``, ``P1 + d y``."""
    p1 = np.asarray(p1, dtype=float)
    return p1 + np.array([[0.0, 0.0, 0.0], [d, 0.0, 0.0], [0.0, d, 0.0]])


def three_point_localization(
    points_world: np.ndarray, p2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs 1-6: base pose from the measured ``M1, M2, M3`` of ``P1, P1 + d x, P1 + d y``.

    ``X = M2 - M1``, ``Y = M3 - M1``, ``Z = X x Y`` (eq 1), normalised (eq 2);
    the paper leaves ``X`` and ``Y`` as measured, here ``Y`` is re-orthogonalised
    as ``Z x X`` so the result is a rotation. The origin is eq 3:
    ``O = M2 - P2x X - P2y Y - P2z Z``.

    Parameters
    ----------
    points_world
        ``(..., 3, 3)`` measured ``M1, M2, M3`` (metres, rows).
    p2
        ``(..., 3)`` the base-frame point ``P2 = P1 + d x``.

    Returns
    -------
    R, t
        ``(..., 3, 3)`` and ``(..., 3)``: the pose of the base in the world.
    """
    Mw = np.asarray(points_world, dtype=float)
    X = Mw[..., 1, :] - Mw[..., 0, :]
    Y = Mw[..., 2, :] - Mw[..., 0, :]
    Z = np.cross(X, Y)
    X = X / np.linalg.norm(X, axis=-1, keepdims=True)
    Z = Z / np.linalg.norm(Z, axis=-1, keepdims=True)
    Y = np.cross(Z, X)
    R = np.stack([X, Y, Z], axis=-1)
    p2 = np.asarray(p2, dtype=float)
    t = Mw[..., 1, :] - np.einsum("...ij,...j->...i", R, p2)
    return R, t


def localize_three_point(
    points_world: Any,
    p1: Any,
    d: float,
    point_cov: Any = None,
    base_sigma: float = 0.0,
    alpha: float = ALPHA,
) -> Registration:
    """Three-point localization (eqs 1-6) with first-order covariance.

    Parameters
    ----------
    points_world
        ``(3, 3)`` measured prism positions at ``P1``, ``P1 + d x``, ``P1 + d y`` (metres).
    p1
        ``(3,)`` the first point in the base frame (metres).
    d
        Step along the base x and y axes (metres, > 0).
    point_cov
        ``(3, 3, 3)`` covariances of the measured points (m^2); zero when None.
    base_sigma
        Robot positioning standard deviation (metres), added to each point.
    alpha
        Level of the tests. The three points give nine coordinates for six
        unknowns: the least-squares fit through them is tested (global test,
        w-tests per point and for scale); a wrong or swapped reading shows there,
        since it cannot be fitted by a rigid motion.
    """
    M = as_points(points_world, "points_world", n=3)
    if not d > 0:
        raise InputError(f"the three-point step d must be positive, got {d}")
    P = three_point_base_points(p1, d)
    check_geometry(M, "points_world")
    R, t = three_point_localization(M, P[1])
    C = np.zeros((3, 3, 3)) if point_cov is None else np.asarray(point_cov, dtype=float)
    C = C + base_sigma**2 * np.eye(3)
    # numerical Jacobian of [d, r] by the 9 measured coordinates (one batched call)
    eps = 1e-6
    Mp = np.repeat(M[None], 9, axis=0)
    Mp.reshape(9, 9)[np.arange(9), np.arange(9)] += eps
    Rp, tp = three_point_localization(Mp, P[1])
    dR = Rp @ R.T
    Jn = np.concatenate([tp - t, log_so3(dR)], axis=1).T / eps
    C9 = np.zeros((9, 9))
    for k in range(3):
        C9[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = C[k]
    cov = Jn @ C9 @ Jn.T
    residuals = M - (P @ R.T + t)
    if np.all(np.linalg.eigvalsh(C)[:, 0] > 0):
        R_fit, t_fit, _ = refine_registration(R, t, P, M, np.linalg.inv(C))
        labels = ["prism P1", "prism P2", "prism P3"]
        tests = point_tests(P, M, C, R_fit, t_fit, np.ones(3, bool), labels, alpha)
        integrity = record(tests, (), alpha)
    else:
        integrity = unchecked("no point covariances: the readings cannot be tested", alpha)
    return Registration(
        T_world_base=make_T(R, t),
        covariance=0.5 * (cov + cov.T),
        residuals=residuals,
        rmse=float(np.sqrt(np.mean(np.einsum("ni,ni->n", residuals, residuals)))),
        method="three_point",
        integrity=integrity,
    )
