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
from typing import Any

import numpy as np

from fabflow.design.elements import Element, structure_timeline
from fabflow.errors import LocalizationError
from fabflow.localize.methods import LOCALIZERS, LocalizeStation, localizer_arguments, run_inputs
from fabflow.localize.setups import InstrumentSetup
from fabflow.localize.site import parking_accuracy
from fabflow.localize.stationing import track_for
from fabflow.positioning.integrity import consistency_tests, exact, guard_exclusion, unchecked
from fabflow.positioning.result import BasePose
from fabflow.project import Project
from fabflow.robots import platform
from fabflow.tasks.plan import Plan, Station
from fabflow.tasks.split import with_pieces
from fabflow.transforms.se3 import compose_covariance, pose_error
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
            integrity=exact("simulation.sensor_noise is false: the pose is the true one"),
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
    setups: Sequence[InstrumentSetup] | None = None,
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
        All elements of the project, as designed or with the plan's print path
        pieces in place of their parents (:func:`~fabflow.tasks.split.with_pieces`,
        applied here when needed).
    rng
        Random generator for the simulated sensors and parking errors.
    method
        Override of the project's localization method.
    setups
        The total station's set-ups (:func:`~fabflow.localize.setups.plan_setups`,
        planned here when needed and absent).

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
    elements = with_pieces(elements, plan.split_elements)
    timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    track = track_for(project, method, plan, elements, setups)
    results: VisitPoses = {}
    previous = None
    drawn = run_inputs(project, method, rng)  # the site's errors, shared by its visits
    for wp, (built, _) in zip(plan.work_packages, timeline, strict=True):
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
            T_planned, T_true = parked_pose(project, wp.station, rng)
            extra: dict[str, Any] = localizer_arguments(project, method, wp.station, built)
            extra.update(drawn)
            if track is not None:
                last = None
                if previous is not None:
                    est, T_last = results[previous.index]
                    last = (T_last, est.T_world_base, est.covariance)
                extra["instrument"] = track.pose_at(wp.index, rng, built, last)
            estimate = localize(project, T_true, rng, wp.station.id, built=built, **extra)
            estimate = check_visit(project, estimate, T_planned)
        results[wp.index] = (estimate, T_true)
        previous = wp
    return results


def parking_covariance(project: Project, T_world_base: np.ndarray) -> np.ndarray:
    """4x4 covariance of the base ``[x, y, z, yaw]`` from the platform's parking accuracy
    (``(..., 4, 4)`` for base poses ``(..., 4, 4)``).

    The platform parks within ``parking_sigma`` per axis and ``parking_sigma_deg``
    in heading (``localization.integrity``; defaults: the simulation's driving
    error); a heading error also moves the base by the lever of the arm mounting.
    The platform stands on the ground, so the base height is known to about
    ``parking_sigma`` too (ground and lift).
    """
    s_xy, s_yaw = parking_accuracy(project)
    lever = np.asarray(T_world_base, dtype=float)[..., :3, :3] @ (
        -project.robot.platform.T_platform_base.matrix()[:3, 3]
    )
    # the base moves by e_z x (base - platform) for a yaw about the platform origin
    J = np.stack([lever[..., 1], -lever[..., 0]], axis=-1)
    C = np.zeros((*J.shape[:-1], 4, 4))
    C[..., :2, :2] = s_xy**2 * np.eye(2) + s_yaw**2 * (J[..., :, None] * J[..., None, :])
    C[..., :2, 3] = C[..., 3, :2] = s_yaw**2 * J
    C[..., 2, 2] = s_xy**2
    C[..., 3, 3] = s_yaw**2
    return C


def check_visit(project: Project, estimate: BasePose, T_world_base_planned: np.ndarray) -> BasePose:
    """The estimate with its integrity completed for the build: finite, tested, where planned.

    - A pose or covariance holding NaN or infinity fails.
    - A method that returned no integrity record fails as untested.
    - A pose that passed its tests only by leaving observations out fails when
      its protection level exceeds the project's position tolerance (the alert
      limit, :func:`~fabflow.positioning.integrity.guard_exclusion`).
    - The estimate must agree with the station the platform was sent to: the
      difference in ``x, y, z, yaw`` is tested against the parking accuracy plus
      the estimate's own covariance (chi-square, 4 dof, at the integrity level).
      The height catches a mirrored solution (tags above anchors that lie almost
      in one plane fit their ranges as well below it).
      A pose farther off means a wrong map, a wrong anchor survey, a wrong
      station, or a platform parked elsewhere: in every case not the pose to
      build from.
    """
    return check_visits(project, [estimate], np.asarray(T_world_base_planned, dtype=float)[None])[0]


def check_visits(
    project: Project, estimates: Sequence[BasePose], T_world_base_planned: np.ndarray
) -> list[BasePose]:
    """:func:`check_visit` of many estimates with their planned base poses ``(n, 4, 4)``:
    the planned-station tests of all of them at once (a simulated run's visits)."""
    integrities = [
        unchecked(f"the {est.method} result carries no tests") if est.integrity is None
        else est.integrity
        for est in estimates
    ]  # fmt: skip
    out = list(estimates)
    tested = []
    for i, (est, integrity) in enumerate(zip(estimates, integrities, strict=True)):
        finite = np.all(np.isfinite(est.T_world_base)) and np.all(np.isfinite(est.covariance))
        if not finite:
            out[i] = replace(
                est, integrity=integrity.failing("the pose or its covariance is not finite")
            )
        elif "exact" in integrity.checks:
            out[i] = replace(est, integrity=integrity)
        else:
            tested.append(i)
    if not tested:
        return out
    planned = np.asarray(T_world_base_planned, dtype=float)[tested]
    err = pose_error(np.stack([estimates[i].T_world_base for i in tested]), planned)
    sel = [0, 1, 2, 5]
    e = err[:, sel]
    own = np.stack([estimates[i].covariance for i in tested])[:, sel][:, :, sel]
    alpha = project.localization.integrity.alpha
    statistic, threshold, passed = consistency_tests(
        e, parking_covariance(project, planned) + own, alpha
    )
    for n, i in enumerate(tested):
        check = {
            "offset_xy_m": float(np.hypot(e[n, 0], e[n, 1])),
            "offset_z_m": float(e[n, 2]),
            "offset_heading_deg": float(np.degrees(e[n, 3])),
            "statistic": float(statistic[n]),
            "threshold": threshold,
            "passed": bool(passed[n]),
        }
        integrity = guard_exclusion(integrities[i], project.tolerances.position)
        integrity = integrity.with_checks(planned_station=check)
        if not check["passed"]:
            integrity = integrity.failing(
                f"the pose is {1e3 * check['offset_xy_m']:.0f} mm (height "
                f"{1e3 * check['offset_z_m']:+.0f} mm) and {abs(check['offset_heading_deg']):.2f} "
                "deg from the planned station, more than the parking accuracy allows: wrong map, "
                "anchor survey or station?"
            )
        out[i] = replace(estimates[i], integrity=integrity)
    return out


def failed_visits(results: VisitPoses) -> list[tuple[int, BasePose]]:
    """The work packages whose pose failed its integrity tests, in order."""
    return [
        (i, est)
        for i, (est, _) in sorted(results.items())
        if est.integrity is None or est.integrity.failed
    ]


def enforce_integrity(project: Project, plan: Plan, results: VisitPoses) -> list[str]:
    """Apply ``localization.integrity.on_failure`` to the localized visits.

    Returns
    -------
    list of str
        One warning per failed visit (``warn``); empty when all passed.

    Raises
    ------
    LocalizationError
        With ``refuse`` (the default), at the first failed visit: naming the
        visit, its station, the method, the test and the suspect observation.
    """
    failed = failed_visits(results)
    if not failed:
        return []
    by_index = {wp.index: wp for wp in plan.work_packages}
    messages = []
    for i, est in failed:
        wp = by_index[i]
        integ = est.integrity
        reason = "untested" if integ is None else integ.reason
        messages.append(
            f"visit {i + 1} at station {wp.station.id} ({est.method}): integrity failed: {reason}"
        )
    if project.localization.integrity.on_failure == "refuse":
        raise LocalizationError(
            messages[0]
            + (f" (and {len(messages) - 1} more visit(s))" if len(messages) > 1 else "")
            + "; no program is written from a failed pose (localization.integrity.on_failure "
            "'warn' builds the others)"
        )
    return messages
