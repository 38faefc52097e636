"""Robot base localization with a robotic total station (paper 001, eqs 1-8).

A prism on the robot's tool is moved to known points ``p_i`` of the robot base
frame (from forward kinematics); the total station measures each one, giving
``m_i`` in the world. The base pose ``T_world_base`` is the rigid motion taking
the ``p_i`` onto the ``m_i``.

Solvers
-------
- :func:`register_points`: the arbitrary-point localization (eqs 7-8). Closed
  form by weighted Kabsch/Umeyama (reflection-safe); with per-point covariances
  (a total station's are needle-shaped along the line of sight) a few
  Gauss-Newton steps then minimise the full Mahalanobis cost. ``method="optimize"``
  solves the paper's constrained problem over ``(O, X, Y)`` with SLSQP instead.
  Either way the result carries the 6x6 covariance (fabflow convention, see
  :mod:`fabflow.positioning.result`), residuals, RMSE and a leave-one-out test
  for a single bad prism reading.
- :func:`three_point_localization` / :func:`localize_three_point`: eqs 1-6 for
  the points ``P1``, ``P1 + d x``, ``P1 + d y``.
- :func:`kabsch`, :func:`refine_registration`, :func:`register_leveled`: the
  batch-capable building blocks (the last one fits a levelled instrument,
  4 DOF, as in a free-station set-up).

Entry points
------------
- :func:`localize_files` / :func:`localize_observations`: measured readings
  (CSV or Leica GSI) against robot points (``fabflow localize total-station``).
- :func:`localize_station`: the simulated instrument used by ``fabflow build``
  and the simulator.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Literal

import numpy as np

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.polar import ARCSEC, Instrument, Observations
from fabflow.positioning.registration import Registration, register_points
from fabflow.transforms.se3 import compose_covariance, inv_T

# --------------------------------------------------------------- observations


def localize_observations(
    observations: Observations,
    robot_ids: Sequence[str],
    robot_points: np.ndarray,
    instrument: Instrument,
    T_world_instrument: np.ndarray | None = None,
    base_sigma: float = 0.0,
    method: Literal["closed_form", "optimize"] = "closed_form",
    reject_outlier: bool = True,
) -> tuple[Registration, tuple[str, ...]]:
    """Register measured observations against robot points matched by point id.

    Parameters
    ----------
    observations
        Polar readings or coordinates from a file (:mod:`fabflow.positioning.ts_io`).
    robot_ids, robot_points
        Ids and ``(n, 3)`` prism positions in the base frame (metres).
    instrument
        Accuracy model used for the point covariances.
    T_world_instrument
        Instrument pose in the world (identity: the instrument frame is the world).
    base_sigma
        Robot positioning standard deviation (metres).
    method, reject_outlier
        As in :func:`register_points`.

    Returns
    -------
    registration, ids
        The result and the matched point ids in the order of its residuals.
    """
    seen: dict[str, int] = {}
    for k, pid in enumerate(observations.point_ids):
        if pid in seen:
            raise InputError(
                f"point id {pid!r} is observed twice",
                observations.source,
                f"line {observations.lines[k]}" if observations.lines else None,
            )
        seen[pid] = k
    index = {pid: k for k, pid in enumerate(robot_ids)}
    matched = [pid for pid in observations.point_ids if pid in index]
    if len(matched) < 3:
        raise LocalizationError(
            f"only {len(matched)} observed point id(s) match the robot points "
            f"(observed: {', '.join(observations.point_ids[:8])}; robot: "
            f"{', '.join(list(robot_ids)[:8])}); need at least 3",
            observations.source,
        )
    M_all, C_all = observations.points(instrument, T_world_instrument)
    rows = np.array([seen[pid] for pid in matched])
    P = np.asarray(robot_points, dtype=float)[[index[pid] for pid in matched]]
    reg = register_points(
        P,
        M_all[rows],
        point_cov=C_all[rows],
        base_sigma=base_sigma,
        method=method,
        reject_outlier=reject_outlier,
    )
    return reg, tuple(matched)


def setup_covariance(sigma_mm: float, sigma_arcsec: float) -> np.ndarray:
    """6x6 covariance of ``T_world_instrument`` from the set-up uncertainty.

    The instrument is levelled by its compensator, so only its position (``sigma_mm``
    per axis) and its orientation about the vertical (``sigma_arcsec``) are uncertain.
    """
    s = sigma_mm * 1e-3
    a = sigma_arcsec * ARCSEC
    return np.diag([s * s, s * s, s * s, 0.0, 0.0, a * a])


def add_instrument_uncertainty(
    reg: Registration, T_world_instrument: np.ndarray, C_world_instrument: np.ndarray
) -> Registration:
    """Add the uncertainty of the instrument pose to a registration made in the world frame.

    The measured world points are ``T_world_instrument`` applied to the
    instrument's readings, so ``T_world_base = T_world_instrument @ T_instrument_base``
    and the set-up error propagates by :func:`~fabflow.transforms.se3.compose_covariance`.
    """
    if not np.any(C_world_instrument):
        return reg
    T_instrument_base = inv_T(T_world_instrument) @ reg.T_world_base
    C = compose_covariance(T_world_instrument, C_world_instrument, T_instrument_base, None)
    return replace(reg, covariance=reg.covariance + 0.5 * (C + C.T))
