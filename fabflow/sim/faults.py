"""Fault injection: do the integrity tests catch what goes wrong on a real site?

Each study places the platform at random stations of a project, simulates the
method's measurements, injects one kind of fault into them, estimates and tests
the base pose as the build does (the method's tests, then the check against the
planned station), and compares the outcome with the truth the simulation knows:

- **detected**: the pose failed its tests;
- **correctly excluded**: it passed after leaving out exactly the faulty observation;
- **silently wrong**: it passed (ok or excluded) although its true error lies
  outside the 99.9 % ellipsoid of its own covariance: what must never happen;
- **false alarm**: on clean data, a pose that failed.

A fault smaller than its minimal detectable bias (MDB, read from a clean solve
of the same station) may pass unnoticed by design; such injections are counted
apart (``below_mdb``), and the protection level bounds their effect.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import special

from fabflow.errors import LocalizationError
from fabflow.localize import icp, uwb
from fabflow.localize import total_station as ts
from fabflow.localize.plan import check_visit, parking_covariance
from fabflow.positioning.result import BasePose
from fabflow.positioning.scan_map import transform_map
from fabflow.project import Project, TotalStationSetup
from fabflow.schema import PoseSpec
from fabflow.transforms.se3 import make_T, perturb, pose_error
from fabflow.transforms.so3 import exp_so3

FAULTS: dict[str, tuple[str, ...]] = {
    "total_station": ("clean", "prism swap", "robot point off", "prism reading off"),
    "uwb": ("clean", "anchor mis-surveyed", "anchor NLOS", "random NLOS", "outside coverage"),
    "icp": ("clean", "start far off", "map shifted 0.3 m", "map shifted 5 cm"),
}
"""The fault kinds of each method's study."""

ELLIPSOID = 1e-3
"""A pose is wrong when its error lies outside the ``1 - ELLIPSOID`` ellipsoid."""


@dataclass(frozen=True)
class FaultOutcome:
    """The tally of one method and fault kind.

    Attributes
    ----------
    method, fault
        What was studied.
    injected
        Stations simulated.
    failed
        Poses that failed their tests (detections; false alarms on clean data).
    excluded, correctly_excluded
        Poses that passed after leaving observations out, and of those the ones
        that left out the faulty observation.
    silently_wrong
        Poses that passed although their error is outside their own ellipsoid.
    below_mdb
        Injections whose fault was smaller than its minimal detectable bias
        (their silent errors are not failures of the tests).
    silently_wrong_above_mdb
        Silently wrong poses among the injections above the MDB (none for
        ``"clean"``). About ``ELLIPSOID * injected`` fall outside the ellipsoid
        by chance even when the fault was found and left out; more would mean
        faults getting through.
    raised
        Stations where no pose could be computed at all (the build stops there).
    median_error_m
        Median horizontal error of the poses that passed (metres).
    """

    method: str
    fault: str
    injected: int
    failed: int
    excluded: int
    correctly_excluded: int
    silently_wrong: int
    below_mdb: int
    silently_wrong_above_mdb: int
    raised: int
    median_error_m: float


STUDY_INSTRUMENT = PoseSpec(xyz=(-3.0, -3.0, 1.6))
"""Where the fault study's total station stands when the project plans its set-ups: one
fixed geometry for every drawn station (the figures of docs/integrity.md were measured
there; a set-up planned per station would change with each draw)."""


def with_method(project: Project, method: str, n_points: int | None = None) -> Project:
    """The project localized by ``method`` (its other setup sections unchanged).

    ``n_points`` sets the number of prism points of a total station setup; a total
    station without a given set-up stands at :data:`STUDY_INSTRUMENT`.
    """
    loc = project.localization.model_copy(update={"method": method})
    if method == "total_station":
        setup = loc.total_station or TotalStationSetup()
        update: dict[str, object] = {}
        if n_points is not None:
            update["n_points"] = n_points
        if setup.T_world_instrument is None:
            update["T_world_instrument"] = STUDY_INSTRUMENT
        loc = loc.model_copy(update={"total_station": setup.model_copy(update=update)})
    return project.model_copy(update={"localization": loc})


def random_station(project: Project, rng: np.random.Generator) -> np.ndarray:
    """A true base pose inside the site's first cabin footprint, random heading (4x4)."""
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    xy = rng.uniform([0.8, 0.8], [3.2, 2.5])
    yaw = rng.uniform(-np.pi, np.pi)
    return make_T(exp_so3([0.0, 0.0, yaw]), [*xy, 0.0]) @ T_platform_base


def _planned(project: Project, T_true: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Where the platform was sent: the true base off by a draw of the parking error."""
    C = parking_covariance(project, T_true)
    C[2, 2] = 0.0  # the simulated platform stands exactly on level ground
    e = rng.multivariate_normal(np.zeros(4), C)
    return perturb(T_true, np.array([e[0], e[1], e[2], 0.0, 0.0, e[3]]))


def _wrong(estimate: BasePose, T_true: np.ndarray) -> bool:
    """Whether the true error lies outside the estimate's ellipsoid (observed axes)."""
    e = pose_error(estimate.T_world_base, T_true)
    C = estimate.covariance
    sel = np.flatnonzero(np.diag(C) < 0.5)  # unobserved axes carry a variance of 1 rad^2
    d2 = float(e[sel] @ np.linalg.pinv(C[np.ix_(sel, sel)]) @ e[sel])
    return d2 > float(special.chdtri(len(sel), ELLIPSOID))


Injected = tuple[Callable[[], BasePose], Callable[[], BasePose], str | None, float]
"""(estimate with the fault, estimate without it, faulty observation label, fault size m)."""


def _total_station_case(
    project: Project, fault: str, T_true: np.ndarray, rng: np.random.Generator
) -> Injected:
    readings = ts.simulate_readings(project, T_true, rng)
    n = len(readings.points_base)
    k = int(rng.integers(n))
    size = 0.0
    faulty = readings
    if fault == "prism swap":
        j = (k + 1 + int(rng.integers(n - 1))) % n
        order = np.arange(n)
        order[[k, j]] = order[[j, k]]
        faulty = dataclasses.replace(
            readings,
            points_world=readings.points_world[order],
            covariances=readings.covariances[order],
        )
        size = float(np.linalg.norm(readings.points_world[k] - readings.points_world[j]))
    elif fault in ("robot point off", "prism reading off"):
        size = 0.05 if fault == "robot point off" else 0.02
        d = rng.normal(size=3)
        d *= size / np.linalg.norm(d)
        field = "points_base" if fault == "robot point off" else "points_world"
        moved = getattr(readings, field).copy()
        moved[k] += d
        faulty = dataclasses.replace(readings, **{field: moved})
    label = None if fault in ("clean", "prism swap") else f"prism P{k + 1}"
    return (
        lambda: ts.estimate_from_readings(project, faulty),
        lambda: ts.estimate_from_readings(project, readings),
        label,
        size,
    )


def _uwb_case(
    project: Project, fault: str, T_true: np.ndarray, rng: np.random.Generator
) -> Injected:
    data = uwb.simulate_station(project, T_true, rng)
    n = len(data.anchor_ids)
    j = int(rng.integers(n))
    anchors = None
    size = 0.0
    faulty = data
    if fault == "anchor mis-surveyed":
        d = rng.normal(size=3)
        anchors = data.anchors_true.copy()
        anchors[j] += 0.5 * d / np.linalg.norm(d)
        # the range bias it causes: the offset along the lines of sight
        u = data.anchors_true[j] - T_true[:3, 3]
        size = abs(float((anchors[j] - data.anchors_true[j]) @ u / np.linalg.norm(u)))
    elif fault == "anchor NLOS":
        r = data.ranges.copy()
        r[:, :, j] += 0.5
        faulty, size = dataclasses.replace(data, ranges=r), 0.5
    elif fault == "random NLOS":
        r = data.ranges.copy()
        hit = rng.random(r.shape) < 0.3
        r[hit] += rng.uniform(0.05, 0.3, int(hit.sum()))
        faulty, size = dataclasses.replace(data, ranges=r), 0.05
    label = (
        f"anchor {data.anchor_ids[j]}" if fault in ("anchor mis-surveyed", "anchor NLOS") else None
    )
    return (
        lambda: uwb.estimate_station(project, faulty, anchors=anchors),
        lambda: uwb.estimate_station(project, data),
        label,
        size,
    )


def _icp_case(
    project: Project, fault: str, T_true: np.ndarray, rng: np.random.Generator
) -> Injected:
    data = icp.simulate_station(project, T_true, rng)
    faulty = data
    direction = rng.normal(size=2)
    direction /= np.linalg.norm(direction)
    if fault == "start far off":
        # beyond the coarse stage's pull-in (0.5 m, 10 deg): odometry gone wrong
        off = np.array([*(1.0 * direction), 0.0, 0.0, 0.0, np.radians(25.0)])
        faulty = dataclasses.replace(data, T_init=perturb(data.T_init, off))
    elif fault.startswith("map shifted"):
        shift = 0.3 if fault.endswith("0.3 m") else 0.05
        T = make_T(np.eye(3), [*(shift * direction), 0.0])
        faulty = dataclasses.replace(data, scan_map=transform_map(data.scan_map, T))
    return (
        lambda: icp.estimate_station(project, faulty),
        lambda: icp.estimate_station(project, data),
        None,
        0.0,
    )


CASES = {"total_station": _total_station_case, "uwb": _uwb_case, "icp": _icp_case}
"""Method name to the function that simulates one faulty station."""


def fault_study(project: Project, method: str, fault: str, n: int, seed: int = 0) -> FaultOutcome:
    """Inject one kind of fault at ``n`` random stations and tally the integrity outcome.

    Parameters
    ----------
    project
        The project (robot, localization setup of ``method``, integrity policy).
    method
        ``"total_station"``, ``"uwb"`` or ``"icp"`` (keys of :data:`FAULTS`).
    fault
        One of ``FAULTS[method]``.
    n
        Stations to simulate.
    seed
        Seed of the study (station ``i`` uses ``seed * 100_000 + i``).
    """
    if fault not in FAULTS.get(method, ()):
        raise ValueError(f"unknown fault {fault!r} for {method!r}")
    counts = dict.fromkeys(
        ("failed", "excluded", "correct", "silent", "below", "silent_above", "raised"), 0
    )
    errors = []
    for i in range(n):
        rng = np.random.default_rng(seed * 100_000 + i)
        T_true = random_station(project, rng)
        if fault == "outside coverage":
            T_true = make_T(np.eye(3), [12.0, 0.0, 0.0]) @ T_true
        T_planned = _planned(project, T_true, rng)
        faulty, clean, label, size = CASES[method](project, fault, T_true, rng)
        try:
            estimate = check_visit(project, faulty(), T_planned)
        except LocalizationError:
            counts["raised"] += 1
            continue
        integ = estimate.integrity
        assert integ is not None
        below = False
        if label is not None:
            mdb = clean().integrity
            below = mdb is not None and size < mdb.mdb.get(label, np.inf)
        counts["below"] += below
        if integ.failed:
            counts["failed"] += 1
            continue
        errors.append(float(np.linalg.norm(pose_error(estimate.T_world_base, T_true)[:2])))
        if integ.status == "excluded":
            counts["excluded"] += 1
            counts["correct"] += label is not None and any(
                e["observation"] == label for e in integ.excluded
            )
        if _wrong(estimate, T_true):
            counts["silent"] += 1
            counts["silent_above"] += fault != "clean" and not below
    return FaultOutcome(
        method=method,
        fault=fault,
        injected=n,
        failed=counts["failed"],
        excluded=counts["excluded"],
        correctly_excluded=counts["correct"],
        silently_wrong=counts["silent"],
        below_mdb=counts["below"],
        silently_wrong_above_mdb=counts["silent_above"],
        raised=counts["raised"],
        median_error_m=float(np.median(errors)) if errors else float("nan"),
    )
