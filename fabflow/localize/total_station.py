"""Total station localization of the robot base: simulated at a station, or from files.

:func:`localize_station` chooses prism points in the base frame (eqs 9-11 of
paper 001, moved clear of the structure and the line of sight; or the
three-point procedure), reaches them with the project's robot
(:mod:`fabflow.robots.prism`), observes them with a simulated instrument
(:mod:`fabflow.sensors.total_station`) and registers the readings
(:mod:`fabflow.positioning.registration`). :func:`localize_files` registers
measured readings (CSV or Leica GSI) against robot points (``fabflow localize
total-station``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from fabflow.design.elements import Element
from fabflow.errors import InputError
from fabflow.localize.prism_points import instrument_for, station_points, total_station_setup
from fabflow.localize.report import check_options
from fabflow.localize.setups import instrument_covariance, plan_setups, trunnion_pose
from fabflow.localize.stationing import InstrumentPose, InstrumentTrack
from fabflow.positioning.adjustment_tests import ALPHA
from fabflow.positioning.polar import (
    Observations,
    polar_covariance,
    polar_to_cartesian,
    to_world,
)
from fabflow.positioning.registration import register_points
from fabflow.positioning.result import BasePose
from fabflow.positioning.three_point import localize_three_point
from fabflow.positioning.total_station import (
    add_instrument_uncertainty,
    localize_observations,
)
from fabflow.positioning.ts_io import RobotPoints, read_observations, read_robot_points
from fabflow.project import Project, TotalStationSetup
from fabflow.robots.catalog import get_robot
from fabflow.robots.prism import prism_points_from_joints
from fabflow.schema import PoseSpec
from fabflow.sensors.total_station import simulate_polar
from fabflow.tasks.plan import Plan, Station, WorkPackage
from fabflow.transforms.se3 import apply_T, inv_T, make_T

MeasuredReadings = tuple[Observations, RobotPoints]
"""The content of a project's measured ``observations`` and ``robot_points`` files."""


@dataclass(frozen=True)
class StationReadings:
    """What a (simulated) total station measured of the prisms at one station.

    Attributes
    ----------
    points_base
        (n, 3) prism positions the robot reports in its base frame (metres).
    points_world
        (n, 3) the measured prism positions in the world (metres).
    covariances
        (n, 3, 3) their covariances (m^2).
    slope_distances
        (n,) measured slope distances (metres).
    T_world_instrument
        4x4 set-up pose of the instrument the readings were turned to the world with.
    moved, dropped
        How the chosen points were moved clear of obstacles, and which were dropped.
    instrument_covariance
        6x6 covariance of ``T_world_instrument``.
    setup
        Id of the instrument set-up.
    """

    points_base: np.ndarray
    points_world: np.ndarray
    covariances: np.ndarray
    slope_distances: np.ndarray
    T_world_instrument: np.ndarray
    moved: np.ndarray
    dropped: tuple[tuple[int, str], ...]
    instrument_covariance: np.ndarray
    setup: str = "T1"


def localize_station(
    project: Project,
    T_world_base: np.ndarray,
    rng: np.random.Generator,
    station_id: str | None = None,
    built: Sequence[Element] = (),
    instrument: InstrumentPose | None = None,
    measured: MeasuredReadings | None = None,
) -> BasePose:
    """Simulate a total station localization of the robot base at one station.

    When the project's setup names measured ``observations`` and
    ``robot_points`` files, those are used instead (:func:`localize_files`;
    ``measured``: their content already read, :func:`measured_readings`)
    and ``T_world_base``, ``rng`` and ``built`` are not.

    Otherwise :func:`simulate_readings` then :func:`estimate_from_readings`: the
    prism points are chosen in the base frame
    (:func:`~fabflow.localize.prism_points.station_points`: eqs 9-11 for the
    ``arbitrary`` procedure, moved clear of ``built`` and of the line of sight;
    ``P1, P1 + d x, P1 + d y`` for ``three_point``), reached by inverse
    kinematics and placed by forward kinematics of the project's robot. The true
    prism positions (plus the robot's repeatability noise) are observed from
    where the instrument really stands with the instrument's noise, turned into
    the world with its registered pose, and the base pose is estimated and
    tested from the readings, the set-up's covariance added.

    Parameters
    ----------
    project
        The project (``localization.total_station``, ``robot``, ``simulation``).
    T_world_base
        True 4x4 pose of the robot base in the world (metres).
    rng
        Source of all noise.
    station_id
        Stored in the result.
    built
        Elements already built (obstacles for the prism, the arm and the line of sight).
    instrument
        The instrument set-up of this visit (:class:`~fabflow.localize.setups.InstrumentTrack`).
        Default: the project's ``T_world_instrument``, or, without one, a set-up
        planned for this station alone.

    Returns
    -------
    BasePose
        Estimated pose with covariance, residuals, quality figures and integrity.
    """
    setup = total_station_setup(project)
    if setup.observations is not None and setup.robot_points is not None:
        # measured readings were supplied: localize from them, nothing is simulated
        return localize_files(
            setup.observations,
            setup.robot_points,
            project=project,
            robot_sigma=project.simulation.robot_repeatability,
            station=station_id,
            readings=measured,
        )
    readings = simulate_readings(project, T_world_base, rng, built, station_id, instrument)
    return estimate_from_readings(project, readings, station_id)


def measured_readings(project: Project) -> MeasuredReadings | None:
    """The project's measured ``observations`` and ``robot_points`` files, read; ``None``
    when it names none (the readings are simulated).

    A Monte Carlo study reads them where it is prepared and hands them to every run
    (:func:`localize_station`'s ``measured``), so that no worker opens the files.

    Raises
    ------
    InputError
        A problem of either file (naming the file and the line).
    """
    setup = total_station_setup(project)
    if setup.observations is None or setup.robot_points is None:
        return None
    return read_observations(setup.observations), read_robot_points(setup.robot_points)


def single_station_instrument(
    project: Project,
    T_world_base: np.ndarray,
    rng: np.random.Generator,
    built: Sequence[Element] = (),
    station_id: str | None = None,
) -> InstrumentPose:
    """The instrument for one station localized on its own: the project's
    ``T_world_instrument``, or the best set-up planned for this station alone."""
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    T_world_platform = np.asarray(T_world_base, dtype=float) @ inv_T(T_platform_base)
    station = Station(station_id or "S1", T_world_platform)
    plan = Plan((WorkPackage(0, station, (), np.zeros((0, 4, 4))),))
    setups = plan_setups(project, plan, list(built), standing=[list(built)])
    pose = InstrumentTrack(project, setups).pose_at(0, rng, built)
    assert pose is not None
    return pose


def simulate_readings(
    project: Project,
    T_world_base: np.ndarray,
    rng: np.random.Generator,
    built: Sequence[Element] = (),
    station_id: str | None = None,
    instrument: InstrumentPose | None = None,
) -> StationReadings:
    """The prism readings of a simulated station (see :func:`localize_station`).

    Raises
    ------
    LocalizationError
        When fewer than three prism points are clear, or no place is clear for
        the three points of the three-point procedure.
    """
    setup = total_station_setup(project)
    if instrument is None:
        instrument = single_station_instrument(project, T_world_base, rng, built, station_id)
    T_world_base = np.asarray(T_world_base, dtype=float)
    chosen = station_points(
        project, T_world_base, built, sight_from=instrument.T_est[:3, 3], station_id=station_id
    )
    P_base = chosen.reach.prism_points(chosen.points)
    sigma_robot = project.simulation.robot_repeatability
    P_true = P_base + rng.normal(0.0, 1.0, P_base.shape) * sigma_robot
    p_instr = apply_T(inv_T(instrument.T_true), apply_T(T_world_base, P_true))
    hz, v, sd = simulate_polar(p_instr, instrument_for(setup), rng)
    M, C = to_world(
        instrument.T_est,
        polar_to_cartesian(hz, v, sd),
        polar_covariance(hz, v, sd, instrument_for(setup)),
    )
    assert C is not None
    return StationReadings(
        P_base,
        M,
        C,
        sd,
        instrument.T_est,
        chosen.moved,
        chosen.dropped,
        instrument.covariance,
        instrument.setup,
    )


def estimate_from_readings(
    project: Project, readings: StationReadings, station_id: str | None = None
) -> BasePose:
    """The base pose from a station's prism readings, tested (see :func:`localize_station`)."""
    setup = total_station_setup(project)
    sigma_robot = project.simulation.robot_repeatability
    P_base, M, C = readings.points_base, readings.points_world, readings.covariances
    policy = project.localization.integrity
    labels = [f"prism P{i + 1}" for i in range(len(P_base))]
    if setup.procedure == "three_point":
        reg = localize_three_point(
            M, P_base[0], setup.three_point_step, C, sigma_robot, policy.alpha
        )
    else:
        reg = register_points(
            P_base,
            M,
            point_cov=C,
            base_sigma=sigma_robot,
            reject_outlier=True,
            alpha=policy.alpha,
            point_labels=labels,
        )
    reg = add_instrument_uncertainty(
        reg, readings.T_world_instrument, readings.instrument_covariance
    )
    quality = {
        "procedure": setup.procedure,
        "instrument_setup": readings.setup,
        "T_world_instrument": readings.T_world_instrument.tolist(),
        "instrument": instrument_for(setup).name,
        "points_base": P_base.tolist(),
        "points_world": M.tolist(),
        "slope_distances": readings.slope_distances.tolist(),
        "moved_for_obstacles": readings.moved.tolist(),
        "dropped_points": [why for _, why in readings.dropped],
    }
    return reg.to_base_pose(station=station_id, quality=quality)


def _three(values: Sequence[float] | None, name: str) -> tuple[float, float, float] | None:
    """Three finite numbers given as ``name`` (or ``None``); anything else is an InputError."""
    if values is None:
        return None
    try:
        v = np.asarray(values, dtype=float).ravel()
    except (TypeError, ValueError):
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InputError(f"{name} must be three finite numbers, got {values!r}")
    return float(v[0]), float(v[1]), float(v[2])


def localize_files(
    observations_path: str | Path,
    robot_points_path: str | Path,
    *,
    project: Project | None = None,
    instrument: str | None = None,
    distance_sigma_mm: float | None = None,
    distance_ppm: float | None = None,
    angle_sigma_arcsec: float | None = None,
    prism_centring_mm: float | None = None,
    atmosphere_ppm: float | None = None,
    instrument_xyz: Sequence[float] | None = None,
    instrument_abc_deg: Sequence[float] | None = None,
    instrument_height: float | None = None,
    robot_sigma: float = 0.0,
    method: Literal["closed_form", "optimize"] = "closed_form",
    reject_outlier: bool = True,
    station: str | None = None,
    robot: str | None = None,
    tcp_xyz: Sequence[float] | None = None,
    readings: MeasuredReadings | None = None,
) -> BasePose:
    """Localize from an observation file and a robot point file (CLI ``localize total-station``).

    The instrument and its pose come from the project's
    ``localization.total_station`` section when ``project`` is given, else from
    the defaults (Leica MS50, instrument frame = world); the keyword arguments
    override either: ``instrument_xyz`` in metres, ``instrument_abc_deg`` in
    degrees (R = Rz(A) Ry(B) Rx(C)). A robot point file of joint values is
    turned into prism positions by forward kinematics of ``robot`` (else the
    project's robot) with the prism at the project's TCP, or at ``tcp_xyz``
    (metres, flange frame). ``readings``: the two files' content already read
    (:func:`measured_readings`); the paths then only name them in the result.

    Raises
    ------
    InputError
        A numeric argument outside :data:`fabflow.localize.report.OPTION_BOUNDS`
        (naming it), or a problem of either file (naming the file and the line).
    LocalizationError
        Too few matching points, or points that do not span a plane.
    """
    instrument_xyz = _three(instrument_xyz, "instrument_xyz")
    instrument_abc_deg = _three(instrument_abc_deg, "instrument_abc_deg")
    tcp_xyz = _three(tcp_xyz, "tcp_xyz")
    check_options(
        {
            "distance_sigma_mm": distance_sigma_mm,
            "distance_ppm": distance_ppm,
            "angle_sigma_arcsec": angle_sigma_arcsec,
            "prism_centring_mm": prism_centring_mm,
            "atmosphere_ppm": atmosphere_ppm,
            "instrument_xyz": instrument_xyz,
            "instrument_abc_deg": instrument_abc_deg,
            "instrument_height": instrument_height,
            "robot_sigma": robot_sigma,
            "tcp_xyz": tcp_xyz,
        }
    )
    setup = TotalStationSetup()
    if project is not None and project.localization.total_station is not None:
        setup = project.localization.total_station
    given = setup.T_world_instrument if project is not None else None
    pose = given if given is not None else PoseSpec()
    # the command line's overrides on the project's setup, then its one accuracy model
    overrides = {
        "instrument": instrument,
        "distance_sigma_mm": distance_sigma_mm,
        "distance_ppm": distance_ppm,
        "angle_sigma_arcsec": angle_sigma_arcsec,
        "prism_centring_mm": prism_centring_mm,
        "atmosphere_ppm": atmosphere_ppm,
    }
    inst = instrument_for(
        setup.model_copy(update={k: v for k, v in overrides.items() if v is not None})
    )
    if instrument_xyz is not None or instrument_abc_deg is not None:
        pose = PoseSpec(
            xyz=instrument_xyz if instrument_xyz is not None else pose.xyz,
            abc_deg=instrument_abc_deg if instrument_abc_deg is not None else pose.abc_deg,
        )
    hi = setup.instrument_height if instrument_height is None else instrument_height
    T_world_instrument = trunnion_pose(pose.matrix(), hi)
    if readings is None:
        readings = read_observations(observations_path), read_robot_points(robot_points_path)
    obs, rp = readings
    if rp.xyz is not None:
        pts = rp.xyz
    else:
        assert rp.joints is not None
        model = robot or (project.robot.name if project is not None else None)
        if model is None:
            raise InputError(
                "the robot point file holds joint values; name the robot (--robot or --project)",
                rp.source,
                f"line {rp.header_line}",
            )
        dof = get_robot(model).dof
        if rp.joints.shape[1] != dof:
            raise InputError(
                f"{model} has {dof} joints but the file gives {rp.joints.shape[1]} "
                f"(q1_deg..q{rp.joints.shape[1]}_deg)",
                rp.source,
                f"line {rp.header_line}",
            )
        T_flange_tool = (
            project.robot.tool.T_flange_tool.matrix() if project is not None else np.eye(4)
        )
        if tcp_xyz is not None:
            T_flange_tool = make_T(T_flange_tool[:3, :3], np.asarray(tcp_xyz, dtype=float))
        pts = prism_points_from_joints(model, rp.joints, T_flange_tool, rp.source, rp.lines)
    reg, matched = localize_observations(
        obs,
        rp.point_ids,
        pts,
        inst,
        T_world_instrument,
        robot_sigma,
        method,
        reject_outlier,
        alpha=ALPHA if project is None else project.localization.integrity.alpha,
        robot_source=rp.source,
    )
    if project is not None:
        reg = add_instrument_uncertainty(reg, T_world_instrument, instrument_covariance(setup))
    quality = {
        "instrument": inst.name,
        "point_ids": list(matched),
        "observations": str(observations_path),
        "robot_points": str(robot_points_path),
        "T_world_instrument": T_world_instrument.tolist(),
    }
    return reg.to_base_pose(station=station, quality=quality)
