"""Total station observations to a base pose (paper 001): matching, set-up uncertainty.

:func:`localize_observations` matches measured readings (polar or coordinates,
from :mod:`fabflow.positioning.ts_io`) to robot points by point id and
registers them (:func:`fabflow.positioning.registration.register_points`);
:func:`add_instrument_uncertainty` adds the uncertainty of the instrument's
set-up (:func:`setup_covariance`) to a registration made in the world frame.
The three-point procedure is :mod:`fabflow.positioning.three_point`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Literal

import numpy as np

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.integrity import ALPHA
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
    alpha: float = ALPHA,
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
    method, reject_outlier, alpha
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
        alpha=alpha,
        point_labels=[f"prism {pid}" for pid in matched],
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
