"""One simulated construction run of a whole project.

Physics of a run (all poses 4x4, metres, world frame):

1. At every visit of the plan the platform parks with the project's driving error
   (:func:`fabflow.localize.plan.parked_pose`): the true base pose ``T_world_base_true``.
2. The localization method simulates its sensors at that pose and estimates the
   base: ``T_world_base_est`` with a 6x6 covariance (:class:`BasePose`). With the
   ``"covariance"`` fidelity the error of the estimate is drawn from the covariance
   calibrated per visit instead (see :func:`prepare_study`). What a real site
   shares between visits is drawn once per run: the total station's set-ups
   (:func:`study_track`), the UWB installation and ICP's simulated map
   (:func:`fabflow.localize.methods.run_inputs`).
3. The robot program is computed in the estimated base frame, so a target
   ``T_world_target`` is commanded as ``inv(T_world_base_est) @ T_world_target`` and
   lands at ``T_world_base_true @ inv(T_world_base_est) @ T_world_target``. The same
   rigid error moves the whole element: ``T_world_element_asbuilt = E @ T_world_element``
   with ``E = T_world_base_true @ inv(T_world_base_est)``.
4. Execution adds the robot's repeatability (isotropic Gaussian, ``robot_repeatability``
   per axis) and the lift's error (vertical Gaussian, ``lift_error``) to every placement.

The plan and the elements are computed once per study (:func:`prepare_study`); a
run only draws random numbers. Run ``i`` of a study with seed ``s`` uses
``numpy.random.default_rng(SeedSequence(s, spawn_key=(i,)))`` (the ``i``-th child
of ``SeedSequence(s)``), so any run can be repeated alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from fabflow.design.elements import Element, Standing, structure_timeline
from fabflow.design.generate import generate_elements
from fabflow.errors import InputError
from fabflow.localize.layout import site_layout
from fabflow.localize.methods import (
    PHASED,
    EstimateStations,
    MeasureStation,
    file_inputs,
    localizer_arguments,
    run_inputs,
)
from fabflow.localize.plan import (
    LocalizeStation,
    check_visit,
    check_visits,
    parked_pose,
    station_localizer,
)
from fabflow.localize.setups import InstrumentSetup
from fabflow.localize.stationing import InstrumentTrack
from fabflow.positioning.result import BasePose
from fabflow.project import LOCALIZATION_METHODS, Project, TotalStationSetup
from fabflow.tasks.plan import Plan, Station
from fabflow.tasks.planner import plan_project
from fabflow.tasks.split import with_pieces
from fabflow.transforms.se3 import exp_T, inv_T, pose_error
from fabflow.transforms.so3 import log_so3

UNOBSERVED_SIGMA = 0.5
"""Predicted sigmas at or above this (radians) mark an axis the method does not
observe (e.g. roll and pitch for UWB)."""

Fidelity = Literal["sensors", "covariance"]
"""How a run localizes: simulated sensors, or a Gaussian draw from the predicted covariance."""

STATIONINGS = ("control_points", "robot_points")
"""How a total station set-up is registered (``localization.total_station.stationing``)."""

CALIBRATION_RUNS = 8
"""Sensor localizations per visit that calibrate the ``"covariance"`` fidelity."""


@dataclass(frozen=True, eq=False)
class Study:
    """Everything a run needs that does not change between runs.

    Attributes
    ----------
    project
        The validated project.
    method
        Localization method simulated (``"uwb"``, ``"total_station"``, ``"icp"``).
    element_ids
        Ids of the N robot-built elements, in build order.
    element_visit
        (N,) index into the visits of the visit that builds each element.
    T_world_element
        (N, 4, 4) planned element poses in the world frame (metres).
    stations
        The station of each of the V visits, in execution order.
    built_before
        Per visit, the elements standing when the platform arrives (pre-built ones
        plus those built on earlier visits); LiDAR scans and UWB lines of sight see them.
    fidelity
        ``"sensors"``: every run simulates the method's sensors at every visit.
        ``"covariance"``: every run draws each visit's base pose error from
        ``visit_covariance`` (a fast Gaussian surrogate, see :func:`prepare_study`).
    visit_covariance
        (V, 6, 6) base pose covariance per visit used by the ``"covariance"`` fidelity
        (axes the method does not observe set to zero); ``None`` for ``"sensors"``.
    setups
        The total station's set-ups (planned once, :mod:`fabflow.localize.setups`);
        ``None`` for the other methods.
    label
        The study's name in reports and output folders: the method, or for a total
        station with a chosen ``stationing``, ``total_station-<stationing>``.
    file_data
        Keyword arguments of the localizer holding the content of the files the
        method reads (ICP's map, the total station's measured readings), read once
        where the study is prepared (:func:`fabflow.localize.methods.file_inputs`):
        the study ships data, not paths, so a worker needs no project file.
    visit_arguments
        Per visit, the method's keyword arguments of the localizer
        (:func:`fabflow.localize.methods.localizer_arguments`: a UWB station's
        ranging zone, ICP's lift), worked out once: they follow from the plan,
        not from a run. Empty: worked out at every visit of every run.
    """

    project: Project
    method: str
    element_ids: tuple[str, ...]
    element_visit: np.ndarray
    T_world_element: np.ndarray
    stations: tuple[Station, ...]
    built_before: tuple[tuple[Element, ...], ...]
    fidelity: Fidelity = "sensors"
    visit_covariance: np.ndarray | None = None
    setups: tuple[InstrumentSetup, ...] | None = None
    label: str = ""
    file_data: dict[str, Any] = field(default_factory=dict)
    visit_arguments: tuple[dict[str, Any], ...] = ()

    @property
    def name(self) -> str:
        """:attr:`label`, or the method."""
        return self.label or self.method

    @property
    def n_elements(self) -> int:
        """Number of robot-built elements N."""
        return len(self.element_ids)

    @property
    def n_visits(self) -> int:
        """Number of visits V."""
        return len(self.stations)

    @property
    def element_station(self) -> list[str]:
        """Station id of each element."""
        return [self.stations[v].id for v in self.element_visit]


def prepare_study(
    project: Project,
    method: str | None = None,
    elements: Sequence[Element] | None = None,
    plan: Plan | None = None,
    fidelity: Fidelity = "sensors",
    calibration_runs: int = CALIBRATION_RUNS,
    stationing: str | None = None,
) -> Study:
    """Generate the elements and plan the project once, for any number of runs.

    With ``fidelity="covariance"`` the method's sensors are simulated only here:
    ``calibration_runs`` times per visit at the planned base pose (seeded from
    ``simulation.seed``), and the mean predicted covariance becomes that visit's
    error model. Runs then draw ``[d, r] ~ N(0, C)`` instead of simulating sensors:
    hundreds of times faster, exact for a method whose predicted covariance is
    honest (see the sigma ratio of a ``"sensors"`` study) and Gaussian, but blind to
    outliers and to run-to-run changes of the geometry. Axes the method does not
    observe (predicted sigma >= 0.5 rad, e.g. roll and pitch for UWB, which assumes
    a level platform) get no error.

    Parameters
    ----------
    project
        The validated project.
    method
        Localization method to simulate (default: ``project.localization.method``).
    elements, plan
        Already computed elements and plan (computed here when absent). The
        elements are the design's: print paths that the plan split into
        per-station pieces are replaced by the pieces it names
        (:func:`fabflow.tasks.split.with_pieces`).
    fidelity
        ``"sensors"`` (default) or ``"covariance"``.
    calibration_runs
        Sensor localizations per visit for the ``"covariance"`` fidelity.
    stationing
        For the total station: how its set-ups are registered, instead of the
        project's ``stationing`` (``control_points``: Procedure B of paper 001,
        ``robot_points``: Procedure A); the study is labelled with it.

    Raises
    ------
    InputError
        For an unknown method or fidelity, or a method whose setup the project lacks.
    LocalizationError
        With ``"covariance"``, when the method fails at a visit's planned pose.
    InfeasibleError
        When the project cannot be planned.
    """
    method = method or project.localization.method
    if fidelity not in ("sensors", "covariance"):
        raise InputError(f"unknown fidelity {fidelity!r}: expected 'sensors' or 'covariance'")
    if method not in LOCALIZATION_METHODS:
        raise InputError(
            f"unknown localization method {method!r}: expected one of "
            + ", ".join(LOCALIZATION_METHODS)
        )
    if method == "uwb" and project.localization.uwb is None:
        raise InputError(
            "method 'uwb' needs a 'localization.uwb' section (its anchors are planned when "
            "it names none)",
            project.path,
            "localization.uwb",
        )
    label = ""
    if stationing is not None and method == "total_station":
        if stationing not in STATIONINGS:
            raise InputError(
                f"unknown stationing {stationing!r}: expected one of " + ", ".join(STATIONINGS),
                location="--stationing",
            )
        ts = project.localization.total_station or TotalStationSetup()
        loc = project.localization.model_copy(
            update={"total_station": ts.model_copy(update={"stationing": stationing})}
        )
        project = project.model_copy(update={"localization": loc})
        label = f"total_station-{stationing}"
    if elements is None:
        elements = generate_elements(project.elements, project.path, project.limits)
    if plan is None:
        plan = plan_project(project, elements)
    elements = with_pieces(elements, plan.split_elements)
    layout = site_layout(project, plan, elements, method)
    project = layout.project
    by_id = {e.id: e for e in elements}
    timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
    ids: list[str] = []
    visit_of: list[int] = []
    built_before: list[tuple[Element, ...]] = []
    for v, (wp, (standing, _)) in enumerate(zip(plan.work_packages, timeline, strict=True)):
        built_before.append(Standing(standing))
        ids += wp.elements
        visit_of += [v] * len(wp.elements)
    T = np.stack([np.asarray(by_id[i].T_world_element, dtype=float) for i in ids])
    study = Study(
        project=project,
        method=method,
        element_ids=tuple(ids),
        element_visit=np.asarray(visit_of, dtype=np.intp),
        T_world_element=T if ids else np.zeros((0, 4, 4)),
        stations=tuple(wp.station for wp in plan.work_packages),
        built_before=tuple(built_before),
        setups=layout.setups,
        label=label,
        file_data=file_inputs(project, method),
        visit_arguments=tuple(
            localizer_arguments(project, method, wp.station, standing)
            for wp, standing in zip(plan.work_packages, built_before, strict=True)
        ),
    )
    if fidelity == "sensors":
        return study
    return replace(
        study,
        fidelity="covariance",
        visit_covariance=calibrate_covariance(study, max(1, calibration_runs)),
    )


def calibrate_covariance(study: Study, n: int) -> np.ndarray:
    """(V, 6, 6) mean predicted base covariance per visit over ``n`` sensor localizations.

    Each visit is localized ``n`` times at its planned base pose, from a generator
    seeded ``[simulation.seed, 0x5EED]`` (independent of every run's stream). Axes
    the method does not observe are zeroed (see :func:`prepare_study`).
    """

    rng = np.random.default_rng([study.project.simulation.seed, 0x5EED])
    localize = study_localizer(study)
    T_platform_base = study.project.robot.platform.T_platform_base.matrix()
    out = np.empty((study.n_visits, 6, 6))
    for v, station in enumerate(study.stations):
        T_planned = station.T_world_base(T_platform_base)
        covs = []
        # a set-up registered on the robot's prisms sees it at its planned previous pose
        T_before = study.stations[max(v - 1, 0)].T_world_base(T_platform_base)
        previous = (T_before, T_before, np.zeros((6, 6)))
        for _ in range(n):
            extra = _localizer_extra(study, v, rng, study_track(study), previous)
            covs.append(
                localize(
                    study.project, T_planned, rng, station.id, study.built_before[v], **extra
                ).covariance
            )
        C = np.mean(covs, axis=0)
        unobserved = np.sqrt(np.clip(np.diag(C), 0.0, None)) >= UNOBSERVED_SIGMA
        C[unobserved, :] = 0.0
        C[:, unobserved] = 0.0
        out[v] = 0.5 * (C + C.T)
    return out


def _cholesky(C: np.ndarray) -> np.ndarray:
    """Factors ``L @ L.T == C`` of PSD matrices (zero rows/columns allowed).

    Components with zero variance get exactly zero rows: the eigenvectors of the
    others may carry rounding-level entries there.
    """
    w, U = np.linalg.eigh(C)
    L = U * np.sqrt(np.clip(w, 0.0, None))[..., None, :]
    return np.where((np.diagonal(C, axis1=-2, axis2=-1) == 0.0)[..., :, None], 0.0, L)


def run_seed(seed: int, run: int) -> np.random.SeedSequence:
    """Seed sequence of run ``run`` of a study seeded ``seed`` (child ``run`` of ``seed``)."""
    return np.random.SeedSequence(seed, spawn_key=(run,))


@dataclass(frozen=True, eq=False)
class RunResult:
    """The outcome of one simulated run.

    Attributes
    ----------
    run
        Run index within the study.
    seed
        Study seed; the run's generator is ``default_rng(run_seed(seed, run))``.
    translation_m
        (N,) distance between as-built and planned element origin (metres).
    rotation_rad
        (N,) rotation angle between as-built and planned element frame (radians).
    deviation_xyz
        (N, 3) as-built minus planned element origin in the world frame (metres).
    localization_error
        (V, 6) error ``[dx, dy, dz, rx, ry, rz]`` of each visit's base estimate
        (true minus estimate, fabflow's convention; metres, radians).
    localization_covariance
        (V, 6, 6) covariance the method predicted for each visit.
    T_world_element_asbuilt
        (N, 4, 4) as-built element poses, when the run was asked to keep them.
    base_poses
        Each visit's :class:`BasePose` estimate, when the run was asked to keep them.
    integrity
        (V,) each visit's integrity status as an index into :data:`STATUSES`.
    """

    run: int
    seed: int
    translation_m: np.ndarray
    rotation_rad: np.ndarray
    deviation_xyz: np.ndarray
    localization_error: np.ndarray
    localization_covariance: np.ndarray
    T_world_element_asbuilt: np.ndarray | None = None
    base_poses: tuple[BasePose, ...] = field(default_factory=tuple)
    integrity: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int8))


STATUSES: tuple[str, ...] = ("ok", "excluded", "failed", "untested")
"""Integrity statuses a simulated visit can end with; ``untested`` for the covariance
fidelity, whose drawn poses are not the result of a solve."""


def study_track(study: Study) -> InstrumentTrack | None:
    """A fresh instrument track for one run (the total station with simulated sensors)."""
    if study.setups is None or not study.project.simulation.sensor_noise:
        return None
    return InstrumentTrack(study.project, study.setups)


def _localizer_extra(
    study: Study,
    v: int,
    rng: np.random.Generator,
    track: InstrumentTrack | None,
    previous: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    drawn: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Keyword arguments of the localizer at visit ``v``: the method's, the data of its
    files (:attr:`Study.file_data`), what the run drew for all its visits
    (``drawn``: :func:`~fabflow.localize.methods.run_inputs`) and the instrument
    set-up standing then (registered when it is put up)."""
    extra: dict[str, Any] = (
        dict(study.visit_arguments[v])
        if study.visit_arguments
        else localizer_arguments(
            study.project, study.method, study.stations[v], study.built_before[v]
        )
    )
    extra.update(study.file_data)
    extra.update(drawn or {})
    if track is not None:
        extra["instrument"] = track.pose_at(v, rng, study.built_before[v], previous)
    return extra


def study_phases(
    study: Study, track: InstrumentTrack | None
) -> tuple[MeasureStation, EstimateStations] | None:
    """The method's measuring and estimating halves (:data:`~fabflow.localize.methods.PHASED`)
    where a run may measure its visits first and estimate them together: sensors
    simulated, and no visit's measurement depending on an earlier visit's estimate
    (a total station tracked from set-up to set-up, the run's ``track``, does)."""
    if not study.project.simulation.sensor_noise or study.visit_covariance is not None:
        return None
    if track is not None:
        return None
    return PHASED.get(study.method)


def study_localizer(study: Study) -> LocalizeStation:
    """The method's ``localize_station``, or an exact one without sensor noise."""
    return station_localizer(study.project, study.method)


def simulate_run(
    study: Study,
    run: int,
    seed: int,
    keep_poses: bool = False,
    localize: LocalizeStation | None = None,
) -> RunResult:
    """Simulate one construction run (see the module docstring for the physics).

    Parameters
    ----------
    study
        The prepared study (:func:`prepare_study`).
    run, seed
        Run index and study seed; they fix every random number of the run.
    keep_poses
        Keep the as-built element poses and the base pose estimates in the result.
    localize
        Localizer to use instead of :func:`study_localizer` (tests; unused with the
        ``"covariance"`` fidelity).

    Raises
    ------
    LocalizationError
        When the method fails at a visit (the Monte Carlo driver records the run as failed).
    """
    rng = np.random.default_rng(run_seed(seed, run))
    sim = study.project.simulation
    track = study_track(study)
    phased = None if localize is not None else study_phases(study, track)
    localize = localize or study_localizer(study)
    V = study.n_visits
    T_true = np.empty((V, 4, 4))
    T_est = np.empty((V, 4, 4))
    cov = np.empty((V, 6, 6))
    estimates: list[BasePose] = []
    status = np.full(V, STATUSES.index("untested"), dtype=np.int8)
    drawn = (
        {} if study.visit_covariance is not None else run_inputs(study.project, study.method, rng)
    )
    T_planned = np.empty((V, 4, 4))

    def take(v: int, estimate: BasePose) -> None:
        """Record visit ``v``'s estimate, checked against its planned station."""
        assert estimate.integrity is not None
        status[v] = STATUSES.index(estimate.integrity.status)
        T_est[v] = estimate.T_world_base
        cov[v] = estimate.covariance
        if keep_poses:
            estimates.append(estimate)

    measured = []
    for v, station in enumerate(study.stations):
        T_planned[v], T_true[v] = parked_pose(study.project, station, rng)
        if study.visit_covariance is not None:
            continue
        previous = None if v == 0 else (T_true[v - 1], T_est[v - 1], cov[v - 1])
        extra = _localizer_extra(study, v, rng, track, previous, drawn)
        if phased is not None:  # measured in order now, estimated together below
            measured.append(
                phased[0](study.project, T_true[v], rng, station.id, study.built_before[v], **extra)
            )
            continue
        estimate = localize(
            study.project, T_true[v], rng, station.id, built=study.built_before[v], **extra
        )
        take(v, check_visit(study.project, estimate, T_planned[v]))
    if phased is not None and measured:
        # a run that keeps no poses reads only their statuses, poses and covariances
        estimated = phased[1](study.project, measured, records=keep_poses)
        for v, estimate in enumerate(check_visits(study.project, estimated, T_planned)):
            take(v, estimate)
    if study.visit_covariance is not None:
        cov[:] = study.visit_covariance
        error = np.einsum("vij,vj->vi", _cholesky(cov), rng.normal(0.0, 1.0, (V, 6)))
        # T_true = perturb(T_est, error): T_est = [Exp(-r) R_true, t_true - d]
        T_est = exp_T(np.concatenate([np.zeros((V, 3)), -error[:, 3:]], axis=1)) @ T_true
        T_est[:, :3, 3] = T_true[:, :3, 3] - error[:, :3]
        if keep_poses:
            estimates = [
                BasePose(
                    T_world_base=T_est[v],
                    covariance=cov[v],
                    method=study.method,
                    station=s.id,
                    quality={"simulated": "drawn from the calibrated covariance"},
                )
                for v, s in enumerate(study.stations)
            ]
    E = T_true @ inv_T(T_est)
    T_asbuilt = E[study.element_visit] @ study.T_world_element
    N = study.n_elements
    noise = rng.normal(0.0, 1.0, (N, 3)) * sim.robot_repeatability
    noise[:, 2] += rng.normal(0.0, 1.0, N) * sim.lift_error
    T_asbuilt[:, :3, 3] += noise
    d = T_asbuilt[:, :3, 3] - study.T_world_element[:, :3, 3]
    dR = T_asbuilt[:, :3, :3] @ np.swapaxes(study.T_world_element[:, :3, :3], -1, -2)
    return RunResult(
        run=run,
        seed=seed,
        translation_m=np.linalg.norm(d, axis=1),
        rotation_rad=np.linalg.norm(log_so3(dR), axis=1),
        deviation_xyz=d,
        localization_error=pose_error(T_est, T_true),
        localization_covariance=cov,
        T_world_element_asbuilt=T_asbuilt if keep_poses else None,
        base_poses=tuple(estimates),
        integrity=status,
    )


def run_to_dict(study: Study, result: RunResult) -> dict[str, Any]:
    """Plain JSON-compatible data of one run: per element and per visit."""
    return {
        "run": result.run,
        "seed": result.seed,
        "method": study.method,
        "elements": [
            {
                "element": eid,
                "station": study.stations[v].id,
                "translation_m": float(t),
                "rotation_rad": float(r),
                "deviation_xyz_m": d.tolist(),
            }
            for eid, v, t, r, d in zip(
                study.element_ids,
                study.element_visit,
                result.translation_m,
                result.rotation_rad,
                result.deviation_xyz,
                strict=True,
            )
        ],
        "visits": [
            {
                "visit": v + 1,
                "station": s.id,
                "error": e.tolist(),
                "sigma": np.sqrt(np.clip(np.diag(c), 0.0, None)).tolist(),
            }
            for v, (s, e, c) in enumerate(
                zip(
                    study.stations,
                    result.localization_error,
                    result.localization_covariance,
                    strict=True,
                )
            )
        ],
    }
