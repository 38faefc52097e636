"""Localize the robot base at every station of a plan with the project's method.

Without measured data, each station is measured with the method's simulated
sensors: the platform parks at its planned pose with the project's driving
error (``simulation.driving_error``), the sensors observe the true base pose,
and the method estimates it. The estimate, with its covariance and residuals,
is what the programs of that station are expressed in.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from fabflow.design.elements import Element
from fabflow.localize.methods import LOCALIZERS, LocalizeStation, localizer_arguments
from fabflow.positioning.result import BasePose
from fabflow.project import Project
from fabflow.robots import platform
from fabflow.tasks.plan import Plan, Station
from fabflow.transforms.se3 import compose_covariance
from fabflow.transforms.so3 import exp_so3

VisitPoses = dict[int, tuple[BasePose, np.ndarray]]
"""Per work package index: the estimated base pose and the true ``T_world_base`` (4x4)."""


def exact_localizer(method: str) -> LocalizeStation:
    """A localizer without sensor noise: the estimate is the true pose, covariance zero."""

    def localize(
        project: Project,
        T_world_base: np.ndarray,
        rng: np.random.Generator,
        station_id: str,
        built: Sequence[Element] = (),
    ) -> BasePose:
        return BasePose(
            T_world_base=np.array(T_world_base, dtype=float),
            covariance=np.zeros((6, 6)),
            method=method,
            station=station_id,
            quality={"simulated": "exact (simulation.sensor_noise is false)"},
        )

    return localize


def station_localizer(project: Project, method: str) -> LocalizeStation:
    """The method's ``localize_station``, or :func:`exact_localizer` when the project's
    ``simulation.sensor_noise`` is off."""
    if not project.simulation.sensor_noise:
        return exact_localizer(method)
    return LOCALIZERS[method]


def parked_pose(
    project: Project, station: Station, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Planned and actual (driving error applied) base pose of a station.

    The platform parks with a Gaussian error of ``simulation.driving_error`` (m)
    in x and y and ``simulation.driving_heading_error_deg`` in heading.

    Returns
    -------
    T_world_base_planned, T_world_base_true
        4x4 poses in the world frame (metres).
    """
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    planned = station.T_world_base(T_platform_base)
    sim = project.simulation
    error = np.eye(4)
    error[:2, 3] = rng.normal(0.0, sim.driving_error, 2)
    error[:3, :3] = exp_so3(
        np.array([0.0, 0.0, rng.normal(0.0, np.radians(sim.driving_heading_error_deg))])
    )
    T_world_platform = station.T_world_platform @ error
    return planned, platform.T_world_base(T_world_platform, station.lift, T_platform_base)


def localize_plan(
    project: Project,
    plan: Plan,
    elements: Sequence[Element],
    rng: np.random.Generator,
    method: str | None = None,
) -> VisitPoses:
    """Localize every station of a plan.

    Parameters
    ----------
    project
        The project (method and setup from ``project.localization``).
    plan
        Stations and the elements built before each visit (for LiDAR scans of the
        structure as built so far).
    elements
        All elements of the project.
    rng
        Random generator for the simulated sensors and parking errors.
    method
        Override of the project's localization method.

    Returns
    -------
    dict
        Work package index (``WorkPackage.index``) to ``(estimated BasePose, true
        T_world_base)``. Every visit to a station parks anew and is localized anew;
        consecutive work packages at one station (the lift moving between them)
        share the visit's measurement, moved by the known lift travel.
    """
    method = method or project.localization.method
    localize = station_localizer(project, method)
    by_id = {e.id: e for e in elements}
    prebuilt = [e for e in elements if not e.robot_built]
    built_ids: list[str] = []
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    results: VisitPoses = {}
    previous = None
    for wp in plan.work_packages:
        if previous is not None and previous.station.id == wp.station.id:
            # Same visit, the lift moved: no new parking, no new measurement.
            estimate, T_true = results[previous.index]
            T_move = platform.lift_move(T_platform_base, previous.station.lift, wp.station.lift)
            T_true = T_true @ T_move
            estimate = replace(
                estimate,
                T_world_base=estimate.T_world_base @ T_move,
                covariance=compose_covariance(
                    estimate.T_world_base, estimate.covariance, T_move, None
                ),
                quality={**estimate.quality, "measured_in_package": previous.index},
            )
        else:
            _, T_true = parked_pose(project, wp.station, rng)
            built = prebuilt + [by_id[i] for i in built_ids]
            estimate = localize(
                project,
                T_true,
                rng,
                wp.station.id,
                built=built,
                **localizer_arguments(project, method, wp.station),
            )
        results[wp.index] = (estimate, T_true)
        built_ids += list(wp.elements)
        previous = wp
    return results
