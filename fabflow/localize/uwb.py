"""UWB localization of a parked platform, simulated for ``fabflow build`` and the simulator.

The platform's tags range to the project's anchors with the sensor model of
:mod:`fabflow.sensors.uwb`; the ranges are calibrated and cleaned, and the
estimator of :mod:`fabflow.positioning.uwb_platform` gives the platform pose,
which the mounting turns into the arm base pose with its covariance.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fabflow.design.elements import Element, element_boxes
from fabflow.errors import InputError
from fabflow.localize.site import anchors_world, points_in_world
from fabflow.localize.uwb_static import static_fixes
from fabflow.positioning.boxes import Boxes, segments_inside
from fabflow.positioning.medians import nanmedian
from fabflow.positioning.result import BasePose
from fabflow.positioning.uwb import UNOBSERVED_VARIANCE, Method
from fabflow.positioning.uwb_calibration import RangeCalibration, Rejection
from fabflow.positioning.uwb_platform import (
    PlatformFix,
    platform_to_base_covariance,
    rejected_ranges,
)
from fabflow.project import Project, UwbSetup
from fabflow.robots import platform
from fabflow.sensors.uwb import (
    AnchorBias,
    UwbErrorModel,
    calibration_campaign,
    draw_bias,
    material_excess,
    segments_occluded,
    simulate_ranges,
)


@dataclass(frozen=True)
class StationRanges:
    """What the tags of a parked platform measured (simulated), and the truth behind it.

    Attributes
    ----------
    anchor_ids
        Anchor names.
    anchors_true
        (n, 3) where the anchors really are (world, metres).
    ranges
        (rounds, tags, anchors) measured ranges, uncorrected (metres).
    calibration
        The ranging calibration fitted by the simulated calibration campaign.
    nlos
        (rounds, tags, anchors) which ranges carry a simulated NLOS excess.
    occluded
        (tags, anchors) lines of sight blocked by built blocks, or ``None``.
    material_length
        (tags, anchors) metres of built material on each line of sight, from the
        design: the estimate predicts the through-material delay from it
        (``uwb.material_delay``); ``None`` when nothing is built or the delay is off.
    """

    anchor_ids: list[str]
    anchors_true: np.ndarray
    ranges: np.ndarray
    calibration: RangeCalibration
    nlos: np.ndarray
    occluded: np.ndarray | None
    material_length: np.ndarray | None = None


@dataclass(frozen=True)
class UwbInstallation:
    """A site's UWB installation as simulated: what every visit of a run shares.

    Attributes
    ----------
    anchor_ids
        The anchors installed (``localization.uwb.anchors``), in the order of
        the arrays below.
    bias
        Per anchor: the range offset and scale and the position-dependent
        multipath field (:func:`~fabflow.sensors.uwb.draw_bias`).
    calibration
        The ranging calibration fitted on the installation's simulated campaign.
    """

    anchor_ids: tuple[str, ...]
    bias: AnchorBias
    calibration: RangeCalibration

    def of(self, ids: Sequence[str]) -> tuple[AnchorBias, RangeCalibration]:
        """The bias and calibration of the anchors ``ids``, in that order.

        Raises
        ------
        InputError
            An anchor that was not installed (an installation drawn for another
            layout).
        """
        index = {k: i for i, k in enumerate(self.anchor_ids)}
        missing = [k for k in ids if k not in index]
        if missing:
            raise InputError(
                f"the UWB installation has no anchor {', '.join(missing)}: it was drawn "
                "for another anchor layout"
            )
        keep = np.array([index[k] for k in ids], dtype=np.intp)
        return self.bias.take(keep), self.calibration.take(keep)


def draw_installation(project: Project, rng: np.random.Generator) -> UwbInstallation:
    """Install the project's anchors: draw their biases and multipath, run the calibration.

    Anchors are put up and calibrated once per site, so the visits of one
    construction run share their errors (``fabflow simulate`` draws one per run,
    :func:`fabflow.localize.methods.run_inputs`).
    """
    setup = _setup(project)
    model = setup.error_model()
    ids = anchors_world(setup)[0]
    bias = draw_bias(len(ids), model, rng)
    cal = RangeCalibration.fit(*calibration_campaign(model, bias, rng))
    return UwbInstallation(tuple(ids), bias, cal)


def localize_station(
    project: Project,
    T_world_base: np.ndarray,
    rng: np.random.Generator,
    station_id: str | None = None,
    built: Sequence[Element] = (),
    heading_prior: tuple[float, float] | None = None,
    zone: Sequence[Sequence[str]] | None = None,
    installation: UwbInstallation | None = None,
) -> BasePose:
    """Simulate UWB localization of a parked platform and return the estimated base pose.

    :func:`simulate_station` then :func:`estimate_station`: the platform stands
    still for ``uwb.dwell_s`` seconds at the true pose; its tags (``uwb.tags``,
    platform frame) range to every anchor at ``uwb.rate_hz`` with the simulator's
    error model (``uwb.error_model()``): distance-dependent noise, the
    position-dependent multipath of each link (``uwb.multipath_sigma``, which
    the dwell does not average out), a per-anchor linear bias (fitted by a
    simulated calibration campaign and corrected), 2 % NLOS outliers, and NLOS
    with probability 0.5 on lines of sight blocked by ``built`` blocks.

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
    zone
        Per tag, the anchors it ranges with (:func:`~fabflow.localize.anchors.ranging_zone`);
        default every anchor.
    installation
        The anchors' biases, multipath and calibration the visit shares with the
        run's others (:func:`draw_installation`); drawn for this visit alone
        when ``None``.

    Returns
    -------
    BasePose
        ``T_world_base`` estimate with a 6x6 covariance and its integrity record;
        roll and pitch are not observed (level platform assumed) and carry
        ``UNOBSERVED_VARIANCE``, as ``quality["unobserved"]`` says.
    """
    measured = measure_station(
        project, T_world_base, rng, station_id, built, heading_prior, zone, installation
    )
    return estimate_measured(project, [measured])[0]


@dataclass(frozen=True)
class MeasuredStation:
    """:func:`localize_station`'s measuring half done: what the tags measured, and
    what the estimate of it needs besides (every random number is drawn)."""

    data: StationRanges
    station_id: str | None
    heading_prior: tuple[float, float] | None


def measure_station(
    project: Project,
    T_world_base: np.ndarray,
    rng: np.random.Generator,
    station_id: str | None = None,
    built: Sequence[Element] = (),
    heading_prior: tuple[float, float] | None = None,
    zone: Sequence[Sequence[str]] | None = None,
    installation: UwbInstallation | None = None,
) -> MeasuredStation:
    """:func:`localize_station`'s measuring half (its parameters): the simulated ranging."""
    data = simulate_station(project, T_world_base, rng, built, zone, installation)
    return MeasuredStation(data, station_id, heading_prior)


def estimate_measured(
    project: Project, measured: Sequence[MeasuredStation], records: bool = True
) -> list[BasePose]:
    """:func:`localize_station`'s estimating half, of many stations at once
    (:func:`estimate_stations`, which takes ``records``); it draws no random number."""
    return estimate_stations(
        project,
        [m.data for m in measured],
        [m.station_id for m in measured],
        [m.heading_prior for m in measured],
        records=records,
    )


def _setup(project: Project) -> UwbSetup:
    setup = project.localization.uwb
    if setup is None:
        raise InputError("the project has no 'localization.uwb' section", location="localization")
    return setup


def simulate_station(
    project: Project,
    T_world_base: np.ndarray,
    rng: np.random.Generator,
    built: Sequence[Element] = (),
    zone: Sequence[Sequence[str]] | None = None,
    installation: UwbInstallation | None = None,
) -> StationRanges:
    """The ranges the platform's tags measure at ``T_world_base`` (see :func:`localize_station`):
    per tag to the anchors of its ``zone`` (default all), with the ``installation``'s
    errors (drawn here when ``None``)."""
    setup = _setup(project)
    ids, A = anchors_world(setup)
    if installation is None:
        installation = draw_installation(project, rng)
    ranged = None
    if zone is not None:
        if len(zone) != len(setup.tags):
            raise InputError(
                f"a ranging zone per tag: {len(setup.tags)} expected, {len(zone)} given"
            )
        unknown = sorted({k for z in zone for k in z} - set(ids))
        if unknown:
            raise InputError(f"ranging zone names unknown anchors: {', '.join(unknown)}")
        ranged = np.array([np.isin(ids, list(z)) for z in zone])
        keep = np.flatnonzero(ranged.any(axis=0))
        ids, A, ranged = [ids[i] for i in keep], A[keep], ranged[:, keep]
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    # the tags are placed from the base pose as given, without the station's lift
    T_world_platform = platform.T_world_platform_of(T_world_base, 0.0, T_platform_base)
    L = np.asarray(setup.tags, dtype=float)
    tags_world = points_in_world(T_world_platform, L)

    model = setup.error_model()
    bias, cal = installation.of(ids)

    T_boxes, ext = element_boxes(built)
    occluded = material = excess = None
    if len(ext):
        starts = np.repeat(tags_world, len(ids), axis=0)
        ends = np.tile(A, (len(L), 1))
        if model.material_delay > 0:  # a line of sight is blocked where it crosses material
            material = segments_inside(starts, ends, Boxes(T_boxes, ext)).reshape(len(L), len(ids))
            occluded = material > 0
            excess = material_excess(model, material, rng)
        else:
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
        link_excess=excess,
    )
    ranges, nlos = sim.ranges, sim.nlos
    if ranged is not None:  # links outside a tag's zone are not ranged
        ranges = np.where(ranged[None], ranges, np.nan)
        nlos = nlos & ranged[None]
        occluded = None if occluded is None else occluded & ranged
    return StationRanges(ids, A, ranges, cal, nlos, occluded, material)


def estimate_station(
    project: Project,
    data: StationRanges,
    station_id: str | None = None,
    heading_prior: tuple[float, float] | None = None,
    anchors: np.ndarray | None = None,
) -> BasePose:
    """The base pose from a station's ranges: calibrate, clean, locate the platform, test.

    Single outliers are rejected around each link's robust centre
    (:func:`~fabflow.positioning.uwb_calibration.reject_outliers_static`;
    counted per link in ``integrity.checks["rejected_ranges"]``), then
    :func:`~fabflow.positioning.uwb_platform.locate_platform` gives ``x, y, z,
    yaw`` with the tests of its integrity record (at
    ``localization.integrity.alpha``); the ranges its tests left out are in
    ``integrity.excluded`` and ``quality["n_left_out_by_tests"]``. An anchor
    left out has no residual RMS: ``quality["per_anchor_rms"]`` holds ``None``.

    Parameters
    ----------
    project
        The project (``localization.uwb``, the arm mounting, the integrity level).
    data
        What the tags measured.
    station_id
        Stored in the result.
    heading_prior
        ``(yaw, sigma)`` of the platform heading (radians); needed with one tag.
    anchors
        (n, 3) the anchor positions the estimate uses (world, metres): the
        surveyed ones; default where they really are.
    """
    return estimate_stations(project, [data], [station_id], [heading_prior], anchors)[0]


def estimate_stations(
    project: Project,
    stations: Sequence[StationRanges],
    station_ids: Sequence[str | None],
    heading_priors: Sequence[tuple[float, float] | None] | None = None,
    anchors: np.ndarray | None = None,
    records: bool = True,
) -> list[BasePose]:
    """:func:`estimate_station` of many stations (a simulated run's visits), in order.

    The stations that range with the same anchors for as many rounds are
    cleaned and corrected together, and their tags' start fixes made in one
    call (:func:`~fabflow.localize.uwb_static.static_fixes`: one call for
    their links where there was one a station), then located one by one. A
    station's pose is the one :func:`estimate_station` gives it alone (to the
    bit with the error model's default noise; with a noise so small that a
    station's NLOS correction integrates on a finer grid, the stations batched
    with it share that grid). With ``records`` False the integrity records
    leave out what cannot change a status, poses or covariances
    (:func:`~fabflow.positioning.uwb_platform.finish_mirror_searches`): for a
    simulated run that keeps none; nor do the poses' residuals and quality.
    """
    setup = _setup(project)
    model = setup.error_model()
    priors = [None] * len(stations) if heading_priors is None else list(heading_priors)
    calibrated = _calibrated(model, stations)
    surveyed = [
        data.anchors_true if anchors is None else np.asarray(anchors, dtype=float)
        for data in stations
    ]
    groups: dict[tuple[Any, ...], list[int]] = {}
    for i, (data, (ranges, link_sigma, _)) in enumerate(zip(stations, calibrated, strict=True)):
        key = (tuple(data.anchor_ids), surveyed[i].tobytes(), ranges.shape, callable(link_sigma))
        groups.setdefault(key, []).append(i)
    out: list[BasePose | None] = [None] * len(stations)
    for members in groups.values():
        first = stations[members[0]]
        link_sigma = calibrated[members[0]][1]
        fixes = static_fixes(
            model,
            surveyed[members[0]],
            np.stack([calibrated[i][0] for i in members], axis=1),
            np.asarray(setup.tags, dtype=float),
            link_sigma if callable(link_sigma) else np.stack([calibrated[i][1] for i in members]),
            np.stack([calibrated[i][2] for i in members]),
            method=_method(setup),
            heading_priors=[priors[i] for i in members],
            alpha=project.localization.integrity.alpha,
            anchor_ids=first.anchor_ids,
            base_lever=project.robot.platform.T_platform_base.matrix()[:3, 3],
            records=records,
        )
        # the base poses and their covariances of all the group's fixes at once
        T_platform_base = project.robot.platform.T_platform_base.matrix()
        T_world_platform = np.stack([fix.T for fix, _ in fixes])
        bases = platform.T_world_base(T_world_platform, 0.0, T_platform_base)
        covs = platform_to_base_covariance(
            T_world_platform, T_platform_base, np.stack([fix.covariance for fix, _ in fixes])
        )
        for n, (i, (fix, rej)) in enumerate(zip(members, fixes, strict=True)):
            out[i] = _base_pose(
                project, stations[i], fix, rej, station_ids[i], bases[n], covs[n], records
            )
    return [pose for pose in out if pose is not None]


def _method(setup: UwbSetup) -> Method:
    """The static estimator of the setup's (the ESKF's stations are static fixes too)."""
    return "wls-t" if setup.estimator in ("wls-t", "eskf") else setup.estimator


def _calibrated(
    model: UwbErrorModel, stations: Sequence[StationRanges]
) -> list[tuple[np.ndarray, Any, np.ndarray]]:
    """Per station, its calibrated ranges (metres), the error its links share (a function
    of the range, or per link with the material's delay taken off) and each anchor's
    remaining calibration error (metres). The median ranges its error is read at are
    one call for the stations of one shape (a simulated run's visits)."""
    out: list[list[Any]] = []
    for data in stations:
        ranges = data.calibration.apply(data.ranges)
        link_sigma: Any = model.field_sigma
        if data.material_length is not None and model.material_delay > 0:
            # the delay the design predicts is taken off; what the site's material
            # may differ by stays in each link's variance, with the multipath's
            predicted = material_excess(model, data.material_length)
            ranges = ranges - predicted[None]
            per_link = nanmedian(ranges, 0)
            link_sigma = np.hypot(
                model.field_sigma(np.where(np.isfinite(per_link), per_link, 0.0)),
                model.material_delay_spread * predicted,
            )
        out.append([ranges, link_sigma])
    shapes: dict[tuple[int, ...], list[int]] = {}
    for i, (ranges, _) in enumerate(out):
        shapes.setdefault(ranges.shape, []).append(i)
    for members in shapes.values():
        guesses = nanmedian(np.stack([out[i][0] for i in members]), (1, 2))
        for i, guess in zip(members, guesses, strict=True):
            cal = stations[i].calibration
            out[i].append(cal.bias_sigma(np.where(np.isfinite(guess), guess, 0.0)))
    return [(ranges, link_sigma, sigma) for ranges, link_sigma, sigma in out]


def _base_pose(
    project: Project,
    data: StationRanges,
    fix: PlatformFix,
    rej: Rejection,
    station_id: str | None,
    T_world_base_est: np.ndarray,
    cov: np.ndarray,
    records: bool = True,
) -> BasePose:
    """The arm base pose ``T_world_base_est`` of a station's platform fix, with its
    covariance ``cov`` (:func:`platform_to_base_covariance`), quality and integrity;
    with ``records`` False without the residuals and the quality (a simulated run
    that keeps no poses reads neither)."""
    removed = rejected_ranges(rej.rejected, data.anchor_ids)
    integrity = fix.integrity and fix.integrity.with_checks(rejected_ranges=removed)
    if not records:
        return BasePose(T_world_base_est, cov, "uwb", station=station_id, integrity=integrity)
    setup = _setup(project)
    ids = data.anchor_ids
    L = np.asarray(setup.tags, dtype=float)
    cal = data.calibration
    method = _method(setup)
    unobserved = ["rx", "ry"] + ([] if fix.heading_observed else ["rz"])
    rmse = float(np.sqrt(np.mean(fix.residuals**2))) if fix.residuals.size else 0.0
    quality: dict[str, Any] = {
        "estimator": method,
        "solver": "joint Gauss-Newton over all ranges"
        if method == "wls-t"
        else f"median of {method} fixes",
        "n_tags": len(L),
        "n_anchors": len(ids),
        "n_rounds": int(data.ranges.shape[0]),
        "n_ranges": int(data.ranges.size),
        "n_rejected_robust_centre": int(rej.rejected.sum()),
        "n_left_out_by_tests": fix.n_ranges - fix.n_used,
        "n_used": fix.n_used,
        "n_nlos_simulated": int(data.nlos.sum()),
        "n_occluded_links": 0 if data.occluded is None else int(data.occluded.sum()),
        "per_anchor_rms": {
            i: float(v) if np.isfinite(v) else None
            for i, v in zip(ids, fix.per_anchor_rms, strict=True)
        },
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
        integrity=integrity,
    )
