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

from fabflow.errors import FabflowError, InputError, LocalizationError
from fabflow.files import show
from fabflow.positioning.adjustment_tests import ALPHA
from fabflow.positioning.polar import ARCSEC, Instrument, Observations
from fabflow.positioning.registration import Registration, register_points
from fabflow.positioning.rigid_fit import check_geometry
from fabflow.transforms.se3 import compose_covariance, inv_T

MAX_PRISM_POINTS = 20
"""Most prism points one localization adjusts. The prism identification tries
every pairwise swap of the readings and the data snooping every point left out
in turn, so the work grows with about the sixth power of the number of points:
20 points take about a second; a station uses 3 to 8."""
MIN_EIGEN_RATIO = 1e-12
"""Smallest ratio of the least to the largest variance of a reading's covariance."""

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
    robot_source: str | None = None,
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
    robot_source
        The file the robot points came from, named in errors about them.

    Returns
    -------
    registration, ids
        The result and the matched point ids in the order of its residuals.

    Raises
    ------
    InputError
        A point id observed twice, more than :data:`MAX_PRISM_POINTS` matched
        points, a reading whose covariance is singular; naming the file (and
        the line).
    LocalizationError
        Fewer than 3 matched points, or points that do not span a plane
        (naming the observation or the robot point file).
    """
    source = observations.source
    seen: dict[str, int] = {}
    for k, pid in enumerate(observations.point_ids):
        if pid in seen:
            raise InputError(f"point id {show(pid)} is observed twice", source, observations.at(k))
        seen[pid] = k
    index = {pid: k for k, pid in enumerate(robot_ids)}
    matched = [pid for pid in observations.point_ids if pid in index]
    if len(matched) < 3:
        raise LocalizationError(
            f"only {len(matched)} observed point id(s) match the robot points "
            f"(observed: {_ids(observations.point_ids)}; robot: {_ids(robot_ids)}); "
            "need at least 3",
            source,
        )
    if len(matched) > MAX_PRISM_POINTS:
        raise InputError(
            f"{len(matched)} readings match robot points; at most {MAX_PRISM_POINTS} are "
            "adjusted in one localization (the tests grow steeply with their number)",
            source,
        )
    M_all, C_all = observations.points(instrument, T_world_instrument)
    rows = np.array([seen[pid] for pid in matched])
    P = np.asarray(robot_points, dtype=float)[[index[pid] for pid in matched]]
    checks = ((P, "robot points", robot_source), (M_all[rows], "readings", source))
    for points, name, where in checks:
        try:
            check_geometry(points, name)
        except LocalizationError as exc:
            raise LocalizationError(exc.message, where) from None
    eig = np.linalg.eigvalsh(C_all[rows] + base_sigma**2 * np.eye(3))
    singular = eig[:, 0] <= MIN_EIGEN_RATIO * eig[:, 2]
    if singular.any():
        k = int(rows[np.argmax(singular)])
        raise InputError(
            f"the reading of {show(observations.point_ids[k])} has a (nearly) singular "
            f"covariance with {instrument.name}'s accuracies (distance and angle sigmas "
            "out of all proportion)",
            source,
            observations.at(k),
        )
    try:
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
    except FabflowError as exc:
        if exc.source is not None:
            raise
        raise type(exc)(exc.message, source, exc.location) from None
    return reg, tuple(matched)


def _ids(ids: Sequence[str]) -> str:
    """The first few ids, each shortened, for a message."""
    shown = ", ".join(show(pid, 16) for pid in list(ids)[:8])
    return shown + (", ..." if len(ids) > 8 else "")


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
