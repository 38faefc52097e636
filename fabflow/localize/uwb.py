"""UWB localization of a parked platform, simulated for ``fabflow build`` and the simulator.

The platform's tags range to the project's anchors with the sensor model of
:mod:`fabflow.sensors.uwb`; the ranges are calibrated and cleaned, and the
estimator of :mod:`fabflow.positioning.uwb_platform` gives the platform pose,
which the mounting turns into the arm base pose with its covariance.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fabflow.design.elements import Element, element_boxes
from fabflow.errors import InputError
from fabflow.localize.site import anchors_world, points_in_world
from fabflow.positioning.result import BasePose
from fabflow.positioning.uwb import UNOBSERVED_VARIANCE, Method
from fabflow.positioning.uwb_calibration import RangeCalibration, reject_outliers_static
from fabflow.positioning.uwb_platform import locate_platform, platform_to_base_covariance
from fabflow.project import Project
from fabflow.robots import platform
from fabflow.sensors.uwb import (
    UwbErrorModel,
    calibration_campaign,
    draw_bias,
    segments_occluded,
    simulate_ranges,
)


def localize_station(
    project: Project,
    T_world_base: np.ndarray,
    rng: np.random.Generator,
    station_id: str | None = None,
    built: Sequence[Element] = (),
    heading_prior: tuple[float, float] | None = None,
) -> BasePose:
    """Simulate UWB localization of a parked platform and return the estimated base pose.

    The platform stands still for ``uwb.dwell_s`` seconds at the true pose; its
    tags (``uwb.tags``, platform frame) range to every anchor at ``uwb.rate_hz``
    with the simulator's error model (:class:`fabflow.sensors.uwb.UwbErrorModel` with
    ``sigma_1m = uwb.sigma``): distance-dependent noise, a per-anchor linear bias
    (fitted by a simulated calibration campaign and corrected), 2 % NLOS outliers,
    and NLOS with probability 0.5 on lines of sight blocked by ``built`` blocks.
    Outliers are rejected around each link's robust centre
    (:func:`~fabflow.positioning.uwb_calibration.reject_outliers_static`), then
    :func:`locate_platform` gives ``x, y, z, yaw``.

    Parameters
    ----------
    project
        The project (``localization.uwb`` and ``robot.platform.T_platform_base``).
    T_world_base
        4x4 true arm base pose (lift included); ``T_world_platform =
        T_world_base @ inv(T_platform_base)``.
    rng
        Random generator (all noise).
    station_id
        Stored in the result.
    built
        Elements already built; blocks occlude lines of sight.
    heading_prior
        ``(yaw, sigma)`` of the platform heading (radians); needed with one tag.

    Returns
    -------
    BasePose
        ``T_world_base`` estimate with a 6x6 covariance; roll and pitch are not
        observed (level platform assumed) and carry ``UNOBSERVED_VARIANCE``, as
        ``quality["unobserved"]`` says.
    """

    setup = project.localization.uwb
    if setup is None:
        raise InputError("the project has no 'localization.uwb' section", location="localization")
    ids, A = anchors_world(setup)
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    # the tags are placed from the base pose as given, without the station's lift
    T_world_platform = platform.T_world_platform_of(T_world_base, 0.0, T_platform_base)
    L = np.asarray(setup.tags, dtype=float)
    tags_world = points_in_world(T_world_platform, L)

    model = UwbErrorModel(sigma_1m=setup.sigma)
    bias = draw_bias(len(ids), model, rng)
    cal = RangeCalibration.fit(*calibration_campaign(model, bias, rng))

    T_boxes, ext = element_boxes(built)
    occluded = None
    if len(ext):
        starts = np.repeat(tags_world, len(ids), axis=0)
        ends = np.tile(A, (len(L), 1))
        occluded = segments_occluded(starts, ends, T_boxes, ext).reshape(len(L), len(ids))

    n_rounds = max(1, round(setup.dwell_s * setup.rate_hz))
    tags_t = np.broadcast_to(tags_world, (n_rounds, *tags_world.shape))
    sim = simulate_ranges(
        A,
        tags_t,
        model,
        rng,
        bias=bias,
        occluded=None
        if occluded is None
        else np.broadcast_to(occluded, (n_rounds, *occluded.shape)),
    )
    ranges = cal.apply(sim.ranges)
    rej = reject_outliers_static(ranges, model.sigma(ranges))
    method: Method = "wls-t" if setup.estimator in ("wls-t", "eskf") else setup.estimator
    dist = np.linalg.norm(tags_world.mean(axis=0) - A, axis=1)
    fix = locate_platform(
        A,
        rej.ranges,
        L,
        model.sigma,
        method=method,
        heading_prior=heading_prior,
        anchor_bias_sigma=cal.bias_sigma(dist),
    )
    T_world_platform_est = fix.T
    T_world_base_est = platform.T_world_base(T_world_platform_est, 0.0, T_platform_base)
    cov = platform_to_base_covariance(T_world_platform_est, T_platform_base, fix.covariance)
    unobserved = ["rx", "ry"] + ([] if fix.heading_observed else ["rz"])
    rmse = float(np.sqrt(np.mean(fix.residuals**2))) if fix.residuals.size else 0.0
    quality: dict[str, Any] = {
        "estimator": method,
        "solver": "joint Gauss-Newton over all ranges"
        if method == "wls-t"
        else f"median of {method} fixes",
        "n_tags": len(L),
        "n_anchors": len(ids),
        "n_rounds": n_rounds,
        "n_ranges": int(sim.ranges.size),
        "n_rejected_robust_centre": int(rej.rejected.sum()),
        "n_rejected_residual": fix.n_ranges - fix.n_used,
        "n_used": fix.n_used,
        "n_nlos_simulated": int(sim.nlos.sum()),
        "n_occluded_links": 0 if occluded is None else int(occluded.sum()),
        "per_anchor_rms": dict(zip(ids, [float(v) for v in fix.per_anchor_rms], strict=True)),
        "calibration": cal.to_dict(ids),
        "std_xyz_yaw": [float(v) for v in np.sqrt(np.diag(fix.covariance))],
        "unobserved": unobserved,
        "unobserved_variance_rad2": UNOBSERVED_VARIANCE,
        "note": "level platform assumed: roll and pitch are not observed by UWB ranging; "
        "covariance: white range noise plus the calibration's remaining per-anchor error",
    }
    return BasePose(
        T_world_base=T_world_base_est,
        covariance=cov,
        method="uwb",
        residuals=fix.residuals[:, None],
        rmse=rmse,
        station=station_id,
        quality=quality,
    )
