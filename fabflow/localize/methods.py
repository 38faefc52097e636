"""The localization methods a project can choose, each a ``localize_station`` function.

:data:`LOCALIZERS` maps the method names of the project schema
(:data:`fabflow.project.LOCALIZATION_METHODS`) to the function that measures
and estimates the robot base at one station: with simulated sensors, or from
the measured files the project names.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

from fabflow.design.elements import Element
from fabflow.localize import icp, total_station, uwb
from fabflow.localize.anchors import ranging_zone
from fabflow.positioning.result import BasePose
from fabflow.project import Project
from fabflow.tasks.plan import Station


class LocalizeStation(Protocol):
    """Measure a base standing at ``T_world_base`` with one method and estimate its pose."""

    def __call__(
        self,
        project: Project,
        T_world_base: np.ndarray,
        rng: np.random.Generator,
        station_id: str,
        built: Sequence[Element] = (),
    ) -> BasePose: ...


LOCALIZERS: dict[str, LocalizeStation] = {
    "uwb": uwb.localize_station,
    "total_station": total_station.localize_station,
    "icp": icp.localize_station,
}
"""Method name (``localization.method``) to its ``localize_station`` function."""


MeasureStation = Callable[..., Any]
"""A localizer's measuring half: called as its ``localize_station`` is, it draws every
random number of a station and returns what its estimating half takes."""

EstimateStations = Callable[..., list[BasePose]]
"""A localizer's estimating half, called as ``(project, measured, records=True)``: the
base poses of what its measuring half measured; with ``records`` False their integrity
records may leave out what cannot change a status, pose or covariance."""

PHASED: dict[str, tuple[MeasureStation, EstimateStations]] = {
    "uwb": (uwb.measure_station, uwb.estimate_measured),
}
"""Methods whose ``localize_station`` is a measuring half that draws every random
number, then an estimating half that draws none: a simulated run measures its
visits in order and estimates them together, in less time and with the numbers
one visit at a time gives (:func:`fabflow.localize.uwb.estimate_stations` says
where they may differ in the last digits)."""

NEEDS_LIFT = frozenset({"icp"})
"""Methods whose sensor does not ride the lift, so the station's lift height places it."""


def localizer_arguments(
    project: Project, method: str, station: Station, built: Sequence[Element] = ()
) -> dict[str, Any]:
    """Method-specific keyword arguments of ``localize_station`` for a station.

    The LiDAR sits on the platform, below the lifted arm base, so ICP needs the
    lift height to place it (:data:`NEEDS_LIFT`). UWB tags range with the
    anchors of the station's zone (:func:`~fabflow.localize.anchors.ranging_zone`,
    from the structure ``built`` before the visit). Without sensor noise the
    localizer is exact and takes none.
    """
    if not project.simulation.sensor_noise:
        return {}
    if method in NEEDS_LIFT:
        return {"lift": station.lift}
    if method == "uwb" and project.localization.uwb is not None:
        zone = ranging_zone(project, station, built)
        return {} if zone is None else {"zone": zone}
    return {}


def file_inputs(project: Project, method: str) -> dict[str, Any]:
    """Keyword arguments of ``localize_station`` that carry the files a method reads, read once.

    ICP's map file (``localization.icp.map``) becomes ``scan_map``
    (:func:`fabflow.localize.icp.file_map`); the total station's measured
    ``observations`` and ``robot_points`` become ``measured``
    (:func:`fabflow.localize.total_station.measured_readings`). A Monte Carlo study
    reads them where it is prepared and sends the data with the study, so that its
    workers open no project file. Empty when the method reads no file, and without
    sensor noise (the exact localizer reads nothing).

    Raises
    ------
    InputError
        An unreadable or malformed file (naming it and the line).
    """
    if not project.simulation.sensor_noise:
        return {}
    if method == "icp":
        scan_map = icp.file_map(project)
        return {} if scan_map is None else {"scan_map": scan_map}
    if method == "total_station":
        measured = total_station.measured_readings(project)
        return {} if measured is None else {"measured": measured}
    return {}


def run_inputs(project: Project, method: str, rng: np.random.Generator) -> dict[str, Any]:
    """Keyword arguments of ``localize_station`` drawn once per simulated construction run:
    what a site's visits share.

    * UWB: the installation (:func:`fabflow.localize.uwb.draw_installation`):
      the anchors' range biases and multipath fields, and the calibration
      fitted on them, are the site's, not a visit's.
    * ICP with a simulated site map (no map file): each run draws its own
      mapping run (:func:`fabflow.localize.icp.site_map` seeded from ``rng``).

    Every fix's covariance counts these errors, but a visit shares them with
    the run's other visits: drawn per visit they would average out of a run,
    and drawn once per study (one map for every run) the study would sample
    one draw of them, not the spread the covariance predicts. Empty for the
    total station (its set-ups are drawn by its own track), with an ICP map
    file, and without sensor noise.

    They are drawn from a generator spawned off ``rng``, so they leave its own
    stream as it was (a run draws its first parking error as the same run of
    another method does).
    """
    if not project.simulation.sensor_noise:
        return {}
    try:
        rng = rng.spawn(1)[0]
    except TypeError:  # a generator without a seed sequence to spawn from
        rng = np.random.default_rng(rng.integers(2**63))
    if method == "uwb":
        return {"installation": uwb.draw_installation(project, rng)}
    if method != "icp":
        return {}
    setup = project.localization.icp
    if setup is not None and setup.map is not None:
        return {}
    return {"scan_map": icp.site_map(project, int(rng.integers(2**32)))}
