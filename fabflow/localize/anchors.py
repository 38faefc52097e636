"""UWB anchor layouts: every station must see anchors around it, in good geometry.

At every work package the platform's tags (``uwb.tags``) range to the anchors.
Through the structure standing then a range is not in sight, and half of such
ranges carry an NLOS excess (the simulator's model,
:class:`fabflow.sensors.uwb.UwbErrorModel`) and are rejected as outliers. The
predicted XY sigma of the platform (its tags' centre) is the Cramer-Rao bound
of its ``x, y, z, yaw`` from one ranging epoch of all its tags, each range
weighted by the chance that it is clean (:func:`_information`): a geometry
figure, as the dilution of precision of satellite positioning is, which a
dwell then averages down. A station is covered when it is within
``target_sigma``, by default :data:`DEFAULT_HDOP` times the range sigma at 1 m
(white noise and multipath together).

:func:`check_anchors` tests a given layout and :func:`coverage_error` names the
first station it does not cover and what to change. :func:`plan_anchors`
places anchors on free ground (a grid of ``anchor_spacing`` at the lowest,
middle and highest ``anchor_height``) counting the ranges in sight alone:
greedily, each time the candidate that most lowers the sum over packages of
what their sigma misses of the target (under a weak prior, so that a package
seeing too few anchors counts),
until every station is covered and at least :data:`MIN_PLANNED` stand (or
``anchor_count`` are placed), starting from an anchor beyond each corner of the
stations' bounding rectangle (a station must stand inside the anchors' hull in
plan, as the UWB fix requires).
:func:`layout_anchors` does the one or the other and returns the project with
its anchors.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fabflow.design.elements import Element, element_boxes, structure_timeline
from fabflow.errors import LocalizationError
from fabflow.localize.site import anchors_world, free_ground, points_in_world
from fabflow.positioning.boxes import Boxes, segments_clear
from fabflow.positioning.uwb import COND_LIMIT, anchor_geometry_problem
from fabflow.positioning.uwb_coverage import COVERAGE_MARGIN, outside_hull
from fabflow.project import Project, UwbSetup
from fabflow.robots import platform
from fabflow.tasks.plan import Plan, Station
from fabflow.transforms.se3 import inv_T

DEFAULT_HDOP = 2.0
"""Default ``target_sigma`` in range sigmas at 1 m (a horizontal dilution of precision of 2,
a common bound of good geometry in satellite and radio positioning)."""
ANCHOR_CLEARANCE = 0.5
"""Distance (metres) a planned anchor keeps from the structure, obstacles and parking places."""
MAX_PLANNED = 40
"""Most anchors :func:`plan_anchors` places."""
MIN_PLANNED = 4
"""Fewest anchors :func:`plan_anchors` places: with three, a faulty anchor leaves no
redundancy to detect it (the integrity tests exclude one anchor at a time)."""
_PRIOR_SIGMA = 10.0
"""Weak prior (metres, radians) on the platform's ``x, y, z, yaw`` in the planner's score."""


@dataclass(frozen=True)
class AnchorCoverage:
    """How well an anchor layout serves every work package.

    Attributes
    ----------
    anchor_ids
        The anchors, in order.
    anchors
        ``(n, 3)`` their positions (world, metres).
    in_sight
        ``(P, T)`` anchors each tag sees past the structure at each package.
    sigma
        ``(P,)`` predicted XY sigma of the platform at each package (metres;
        infinity when the ranges do not fix it).
    sigma_in_sight
        ``(P,)`` the same from the ranges in sight alone.
    target
        The target sigma (metres).
    planned
        Whether the layout was planned (else given and checked).
    in_sight_possible
        ``(P,)`` for a planned layout: the packages any anchors on the site could
        cover in sight (deep inside a finished building, no place can).
    outside
        ``(P,)`` how far the tags' centre stands outside the anchors' convex hull in
        plan (metres): beyond ``COVERAGE_MARGIN`` the UWB fix fails its tests.
    """

    anchor_ids: tuple[str, ...]
    anchors: np.ndarray
    in_sight: np.ndarray
    sigma: np.ndarray
    sigma_in_sight: np.ndarray
    target: float
    planned: bool
    in_sight_possible: np.ndarray | None = None
    outside: np.ndarray | None = None

    @property
    def judged(self) -> np.ndarray:
        """``(P,)`` the sigma each package is judged by: a planned layout must reach the
        target with ranges in sight alone, where any anchor on the site could."""
        if not self.planned:
            return self.sigma
        possible = self.in_sight_possible
        if possible is None:
            possible = np.ones(len(self.sigma), dtype=bool)
        return np.where(possible, self.sigma_in_sight, self.sigma)

    @property
    def covered(self) -> np.ndarray:
        """``(P,)`` packages whose judged sigma is within the target, inside the anchors'
        plan hull (within :data:`~fabflow.positioning.uwb_coverage.COVERAGE_MARGIN`)."""
        inside = np.ones(len(self.sigma), dtype=bool)
        if self.outside is not None:
            inside = self.outside <= COVERAGE_MARGIN
        return (self.judged <= self.target) & inside

    @property
    def through_structure(self) -> np.ndarray:
        """``(P,)`` packages that reach the target only with ranges through the structure."""
        return self.covered & (self.sigma_in_sight > self.target)

    def to_dict(self, stations: Sequence[str]) -> dict[str, Any]:
        """Plain JSON-compatible data (``uwb_anchors.json``)."""
        return {
            "frame": "world",
            "units": "m",
            "planned": self.planned,
            "target_sigma_xy_m": self.target,
            "anchors": {k: p.tolist() for k, p in zip(self.anchor_ids, self.anchors, strict=True)},
            "packages": [
                {
                    "package": k + 1,
                    "station": stations[k],
                    "anchors_in_sight_per_tag": self.in_sight[k].tolist(),
                    "sigma_xy_m": _finite(self.sigma[k]),
                    "sigma_xy_in_sight_m": _finite(self.sigma_in_sight[k]),
                }
                for k in range(len(self.sigma))
            ],
        }


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def _setup(project: Project) -> UwbSetup:
    """The project's ``localization.uwb`` (every caller here plans or checks UWB)."""
    setup = project.localization.uwb
    assert setup is not None
    return setup


def target_sigma(project: Project) -> float:
    """``uwb.target_sigma``, or :data:`DEFAULT_HDOP` x the range sigma at 1 m, ``uwb.sigma``
    and ``uwb.multipath_sigma`` together (metres)."""
    setup = _setup(project)
    if setup.target_sigma is not None:
        return setup.target_sigma
    return DEFAULT_HDOP * float(np.hypot(setup.sigma, setup.multipath_sigma))


def package_tags(project: Project, plan: Plan) -> np.ndarray:
    """``(P, T, 3)`` tag positions at each work package (world, metres), placed from the
    package's base pose as :func:`fabflow.localize.uwb.simulate_station` places them."""
    L = len(_setup(project).tags)
    out = [station_tags(project, wp.station) for wp in plan.work_packages]
    return np.asarray(out).reshape(len(plan.work_packages), L, 3)


def station_tags(project: Project, station: Station) -> np.ndarray:
    """``(T, 3)`` the tag positions at a planned station (world, metres)."""
    L = np.asarray(_setup(project).tags, dtype=float)
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    T_base = station.T_world_base(T_platform_base)
    return points_in_world(platform.T_world_platform_of(T_base, 0.0, T_platform_base), L)


def _tags_fix_themselves(tags: np.ndarray, anchors: np.ndarray, sight: np.ndarray) -> bool:
    """Whether every tag ``(T, 3)`` sees :data:`MIN_PLANNED` anchors (``sight``: ``(T, A)``),
    not in one plane, whose directions condition its 3D position as the per-tag
    fixes require (:data:`~fabflow.positioning.uwb.COND_LIMIT`)."""
    if sight.sum(axis=1).min() < MIN_PLANNED:
        return False
    # the per-tag fixes start from differences of squared ranges: not in one plane
    if any(anchor_geometry_problem(anchors[row]) is not None for row in sight):
        return False
    diff = anchors[None] - tags[:, None]
    u = diff / np.linalg.norm(diff, axis=2, keepdims=True)
    N = np.einsum("ta,tai,taj->tij", sight.astype(float), u, u)
    ev = np.linalg.eigvalsh(N)
    return bool(np.all(ev[:, 0] > ev[:, -1] / COND_LIMIT))


def ranging_zone(
    project: Project, station: Station, built: Sequence[Element]
) -> tuple[tuple[str, ...], ...] | None:
    """The anchors each tag ranges with at a planned station: its zone, or ``None`` (all).

    A site's UWB system assigns each area the anchors that serve it (the zones of
    an RTLS), so that a platform does not range through the buildings to anchors
    across the site, where half of the ranges carry an NLOS excess (too many for
    the robust centre of a link to reject) and several faulty links at once
    defeat the one-at-a-time exclusion of the tests. Each tag's zone is the
    anchors it sees past the structure ``built``, at the station as planned.
    Where those do not serve, the anchors hidden from a tag join its zone one at
    a time (those hidden from the fewest tags first, then the nearest), until
    the zone does (:func:`_zone_serves`): each tag fixes itself from its zone,
    the tags' centre stands inside the zone's plan hull and the zone reaches the
    target sigma, its ranges through the structure counted with their NLOS
    chance. A zone that needs every anchor is ``None``, as where every anchor is
    in sight.

    Returns
    -------
    tuple or None
        Per tag (in ``uwb.tags`` order) the ids of the anchors it ranges with.
    """
    setup = _setup(project)
    ids, anchors = anchors_world(setup)
    tags = station_tags(project, station)
    sight = _sight(tags[None], anchors, [built])[0]  # (T, A)
    hidden = np.flatnonzero(~sight.all(axis=0))
    distance = np.linalg.norm(anchors[hidden] - tags.mean(axis=0), axis=1)
    order = hidden[np.lexsort((distance, (~sight[:, hidden]).sum(axis=0)))]
    ranged = sight.copy()
    for joined in order:
        if _zone_serves(project, tags, anchors, sight, ranged):
            return tuple(tuple(ids[i] for i in np.flatnonzero(row)) for row in ranged)
        ranged[:, joined] = True
    return None


def _zone_serves(
    project: Project, tags: np.ndarray, anchors: np.ndarray, sight: np.ndarray, ranged: np.ndarray
) -> bool:
    """Whether the tags ``(T, 3)`` ranging with ``ranged`` ``(T, A)`` of the anchors, of
    which they see ``sight``, fix themselves, stand inside the plan hull of the anchors
    ranged (within :data:`~fabflow.positioning.uwb_coverage.COVERAGE_MARGIN`) and reach
    the target sigma."""
    if not _tags_fix_themselves(tags, anchors, ranged):
        return False
    zone = ranged.any(axis=0)
    if outside_hull(anchors[zone, :2], tags.mean(axis=0)[None, :2])[0] > COVERAGE_MARGIN:
        return False
    info = _information(
        project, tags[None], anchors[zone], sight[None][:, :, zone], ranged[:, zone]
    )
    return bool(_sigma_xy(info.sum(axis=1))[0] <= target_sigma(project))


def _sight(
    tags: np.ndarray, anchors: np.ndarray, standing: Sequence[Sequence[Element]]
) -> np.ndarray:
    """``(P, T, A)`` whether each tag sees each anchor past the structure standing at
    each package."""
    P, T = tags.shape[:2]
    A = len(anchors)
    sight = np.zeros((P, T, A), dtype=bool)
    for k, built in enumerate(standing):
        T_box, extents = element_boxes(built)
        boxes = Boxes(T_box, extents) if len(extents) else Boxes.empty()
        starts = np.repeat(tags[k], A, axis=0)
        ends = np.tile(anchors, (T, 1))
        sight[k] = segments_clear(starts, ends, boxes).reshape(T, A)
    return sight


def _information(
    project: Project,
    tags: np.ndarray,
    anchors: np.ndarray,
    sight: np.ndarray,
    ranged: np.ndarray | None = None,
) -> np.ndarray:
    """Per package and anchor the expected Fisher information of one epoch of its
    ranges on the platform's ``x, y, z, yaw``, ``(P, A, 4, 4)``.

    Each range has the simulator's distance-dependent noise and multipath (the
    multipath is in every epoch, and is what a dwell does not average away) and
    counts with the chance it carries no NLOS excess (``1 - nlos_prob`` in sight, ``1 -
    nlos_prob_occluded`` through the structure); only the links ``ranged``
    (broadcast to ``sight``; default all) count.
    """
    setup = _setup(project)
    P, T = tags.shape[:2]
    A = len(anchors)
    model = setup.error_model()
    diff = tags[:, :, None, :] - anchors[None, None]  # (P, T, A, 3)
    dist = np.linalg.norm(diff, axis=-1)
    u = diff / np.maximum(dist, 1e-9)[..., None]
    clean = 1.0 - np.where(sight, model.nlos_prob, model.nlos_prob_occluded)
    if ranged is not None:
        clean = np.where(ranged, clean, 0.0)
    weight = clean / (model.sigma(dist) ** 2 + model.field_sigma(dist) ** 2)  # (P, T, A)
    # d range / d (x, y, z, yaw): the tag's lever turns with the platform's heading
    lever = tags - tags.mean(axis=1, keepdims=True)
    J = np.zeros((P, T, A, 4))
    J[..., :3] = u
    J[..., 3] = u[..., 0] * -lever[:, :, None, 1] + u[..., 1] * lever[:, :, None, 0]
    return np.einsum("ptai,pta,ptaj->paij", J, weight, J)


def _sigma_xy(info: np.ndarray) -> np.ndarray:
    """XY sigma (metres) of the tags' centre from summed ``(..., 4, 4)`` information on
    ``x, y, z, yaw``; infinity where singular."""
    flat = info.reshape(-1, 4, 4)
    out = np.full(len(flat), np.inf)
    ev = np.linalg.eigvalsh(flat)
    ok = ev[:, 0] > 1e-9 * np.maximum(ev[:, -1], 1e-300)
    C = np.linalg.inv(flat[ok])
    out[ok] = np.sqrt(C[:, 0, 0] + C[:, 1, 1])
    return out.reshape(info.shape[:-2])


def _standing(plan: Plan, elements: Sequence[Element]) -> list[list[Element]]:
    timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
    return [list(built) for built, _ in timeline]


def check_anchors(
    project: Project,
    plan: Plan,
    elements: Sequence[Element],
    anchors: np.ndarray | None = None,
    planned: bool = False,
    in_sight_possible: np.ndarray | None = None,
) -> AnchorCoverage:
    """The coverage of the project's anchors (or ``anchors``, world) at every work package.

    ``planned``: the layout was planned; ``in_sight_possible``: ``(P,)`` the packages
    the planner could cover with ranges in sight (see :class:`AnchorCoverage`).
    """
    setup = _setup(project)
    if anchors is None:
        ids, anchors = anchors_world(setup)
    else:
        ids = [f"A{i + 1}" for i in range(len(anchors))]
    tags = package_tags(project, plan)
    sight = _sight(tags, anchors, _standing(plan, elements))
    info = _information(project, tags, anchors, sight)
    info_in_sight = _information(project, tags, anchors, sight, ranged=sight)
    outside = outside_hull(np.asarray(anchors)[:, :2], tags.mean(axis=1)[:, :2])
    return AnchorCoverage(
        tuple(ids),
        np.asarray(anchors, dtype=float),
        sight.sum(axis=2),
        _sigma_xy(info.sum(axis=1)),
        _sigma_xy(info_in_sight.sum(axis=1)),
        target_sigma(project),
        planned,
        in_sight_possible,
        outside,
    )


def coverage_error(coverage: AnchorCoverage, plan: Plan) -> str | None:
    """A message naming the first work package the layout does not cover, or None."""
    bad = np.flatnonzero(~coverage.covered)
    if len(bad) == 0:
        return None
    k = int(bad[0])
    station = plan.work_packages[k].station.id
    sigma = coverage.judged[k]
    shown = f"{1000 * sigma:.1f} mm" if np.isfinite(sigma) else "undetermined"
    fix = (
        "raise localization.uwb.anchor_count or anchor_height, or give the anchors"
        if coverage.planned
        else "add or move anchors in localization.uwb.anchors, or remove them to have them planned"
    )
    seen = ", ".join(str(int(v)) for v in coverage.in_sight[k])
    out = 0.0 if coverage.outside is None else float(coverage.outside[k])
    if out > COVERAGE_MARGIN:
        return (
            f"UWB anchors do not cover station {station} (work package {k + 1}; {len(bad)} "
            f"package(s) in all): the platform stands {out:.1f} m outside the anchors' "
            f"convex hull in plan (at most {COVERAGE_MARGIN:g} m); {fix}"
        )
    return (
        f"UWB anchors do not cover station {station} (work package {k + 1}; {len(bad)} "
        f"package(s) in all): predicted XY sigma {shown}, target "
        f"{1000 * coverage.target:.1f} mm (localization.uwb.target_sigma); anchors in sight "
        f"past the structure per tag: {seen}; {fix}"
    )


def plan_anchors(
    project: Project, plan: Plan, elements: Sequence[Element]
) -> tuple[np.ndarray, np.ndarray]:
    """Planned anchor positions ``(n, 3)`` (world, metres), and ``(P,)`` the packages any
    candidate layout could cover in sight; see the module docstring. A package no
    anchor on the site sees well enough is planned for with its ranges through the
    structure counted as in :func:`check_anchors`.

    Raises
    ------
    LocalizationError
        When no free ground is left for anchors.
    """
    setup = _setup(project)
    xy = free_ground(project, elements, plan, setup.anchor_spacing, ANCHOR_CLEARANCE)
    if len(xy) == 0:
        raise LocalizationError(
            "no free ground on the site for UWB anchors: enlarge site.extent_min/max"
        )
    lo, hi = setup.anchor_height
    heights = np.unique([lo, 0.5 * (lo + hi), hi])
    cands = np.concatenate([np.column_stack([xy, np.full(len(xy), h)]) for h in heights])
    tags = package_tags(project, plan)
    sight = _sight(tags, cands, _standing(plan, elements))
    in_sight = _information(project, tags, cands, sight, ranged=sight)
    target = target_sigma(project)
    possible = _sigma_xy(in_sight.sum(axis=1)) <= target
    info = in_sight
    if not possible.all():
        mixed = _information(project, tags, cands, sight)
        info = np.where(possible[:, None, None, None], in_sight, mixed)
    limit = setup.anchor_count or MAX_PLANNED
    chosen = _corner_anchors(cands, tags.mean(axis=1)[:, :2])[:limit]
    # a weak prior keeps the score finite while a package sees too few anchors, so
    # every anchor that helps an uncovered package lowers it
    total = np.zeros((info.shape[0], 4, 4)) + np.eye(4) / _PRIOR_SIGMA**2
    free = np.ones(len(cands), dtype=bool)
    for best in chosen:
        free[best] = False
        total += info[:, best]
    while len(chosen) < limit:
        idx = np.flatnonzero(free)
        C = np.linalg.inv(total[None] + np.moveaxis(info[:, idx], 1, 0))  # (C, P, 4, 4)
        sigma = np.sqrt(C[..., 0, 0] + C[..., 1, 1])
        # what is still missing where the target is not met; among equals the sum
        score = np.maximum(sigma - target, 0.0).sum(axis=1) + 1e-3 * sigma.sum(axis=1)
        best = int(idx[int(np.argmin(score))])
        chosen.append(best)
        free[best] = False
        total += info[:, best]
        enough = len(chosen) >= MIN_PLANNED
        covered = _sigma_xy(total - np.eye(4) / _PRIOR_SIGMA**2) <= target
        if setup.anchor_count is None and enough and covered.all():
            break
    if setup.anchor_count is None:
        chosen += _enclosing_anchors(cands, chosen, sight, tags.mean(axis=1), possible, limit)
    return cands[chosen], possible


def _enclosing_anchors(
    cands: np.ndarray,
    chosen: list[int],
    sight: np.ndarray,
    centres: np.ndarray,
    possible: np.ndarray,
    limit: int,
) -> list[int]:
    """Anchors added (candidate indices) so that every package the site can cover in
    sight stands inside the plan hull of the anchors its tags see, as its ranging zone
    needs (:func:`ranging_zone`): while one is outside, for the one farthest outside,
    the free candidate in its sight nearest the middle of the widest angular gap of
    its anchors seen from it (``sight``: ``(P, T, C)``; ``centres``: ``(P, 3)``)."""
    seen = sight.any(axis=1)  # (P, C)
    added: list[int] = []
    hopeless = ~possible
    while len(chosen) + len(added) < limit:
        have = np.array(chosen + added)
        outside = np.zeros(len(centres))
        for p in np.flatnonzero(~hopeless):
            mine = have[seen[p, have]]
            if len(mine) >= 3:
                outside[p] = outside_hull(cands[mine, :2], centres[p, :2])[0]
        if outside.max() <= COVERAGE_MARGIN:
            break
        p = int(np.argmax(outside))
        mine = cands[have[seen[p, have]], :2] - centres[p, :2]
        angle = np.sort(np.arctan2(mine[:, 1], mine[:, 0]))
        gaps = np.diff(np.append(angle, angle[0] + 2 * np.pi))
        k = int(np.argmax(gaps))
        middle = angle[k] + 0.5 * gaps[k]
        free = np.ones(len(cands), dtype=bool)
        free[have] = False
        idx = np.flatnonzero(free & seen[p])
        if len(idx) == 0:
            hopeless[p] = True
            continue
        rel = cands[idx, :2] - centres[p, :2]
        off = np.abs(np.angle(np.exp(1j * (np.arctan2(rel[:, 1], rel[:, 0]) - middle))))
        if off.min() >= 0.5 * gaps[k]:  # nothing in sight within the gap
            hopeless[p] = True
            continue
        added.append(int(idx[np.lexsort((np.linalg.norm(rel, axis=1), np.round(off, 2)))[0]]))
    return added


def _corner_anchors(cands: np.ndarray, stations_xy: np.ndarray) -> list[int]:
    """Candidates that put every station inside the anchors' plan hull: for each corner
    of the stations' bounding rectangle, the candidate nearest it beyond it, at the
    highest and the lowest height in turn (the UWB fix fails a platform outside the
    hull, and anchors in one plane)."""
    lo, hi = stations_xy.min(axis=0), stations_xy.max(axis=0)
    top = cands[:, 2] >= cands[:, 2].max() - 1e-9
    bottom = cands[:, 2] <= cands[:, 2].min() + 1e-9
    out: list[int] = []
    # diagonal corners high, the other two low: the anchors must not lie in one plane
    for sx, sy, level in ((-1, -1, top), (1, -1, bottom), (1, 1, top), (-1, 1, bottom)):
        corner = np.array([hi[0] if sx > 0 else lo[0], hi[1] if sy > 0 else lo[1]])
        side = (sx * (cands[:, 0] - corner[0]) >= 0) & (sy * (cands[:, 1] - corner[1]) >= 0)
        beyond = level & side
        if beyond.any():
            idx = np.flatnonzero(beyond)
            k = int(idx[np.argmin(np.linalg.norm(cands[idx, :2] - corner, axis=1))])
            if k not in out:
                out.append(k)
    return out


def layout_anchors(
    project: Project, plan: Plan, elements: Sequence[Element]
) -> tuple[Project, AnchorCoverage]:
    """The project with its UWB anchors (planned when it names none) and their coverage.

    Raises
    ------
    LocalizationError
        When the anchors, given or planned, leave a station uncovered
        (:func:`coverage_error`).
    """
    setup = _setup(project)
    if setup.anchors:
        coverage = check_anchors(project, plan, elements)
    else:
        world, possible = plan_anchors(project, plan, elements)
        coverage = check_anchors(project, plan, elements, world, True, possible)
        local = points_in_world(inv_T(setup.T_world_uwb.matrix()), world)
        anchors = {
            k: tuple(float(v) for v in p) for k, p in zip(coverage.anchor_ids, local, strict=True)
        }
        uwb = setup.model_copy(update={"anchors": anchors})
        project = project.model_copy(
            update={"localization": project.localization.model_copy(update={"uwb": uwb})}
        )
    problem = anchor_geometry_problem(coverage.anchors)
    if problem is not None:
        problem = f"localization.uwb.anchors: {problem}"
    message = problem or coverage_error(coverage, plan)
    if message is not None:
        raise LocalizationError(message)
    return project, coverage


def anchor_rows(coverage: AnchorCoverage, plan: Plan) -> list[tuple[str, str]]:
    """Build summary rows: the layout, and its worst station."""
    sigma = coverage.judged
    k = int(np.argmax(sigma))
    how = "planned" if coverage.planned else "given, checked"
    rows = [
        ("UWB anchors", f"{len(coverage.anchor_ids)} ({how})"),
        (
            "UWB predicted XY sigma (max)",
            f"{1000 * sigma[k]:.1f} mm at station {plan.work_packages[k].station.id} "
            f"(target {1000 * coverage.target:.1f} mm; fewest anchors in sight of a tag: "
            f"{int(coverage.in_sight.min())})",
        ),
    ]
    nlos = np.flatnonzero(coverage.through_structure)
    if len(nlos):
        rows.append(
            (
                "UWB through the structure",
                f"{len(nlos)} of {len(sigma)} packages (first: {nlos[0] + 1}, station "
                f"{plan.work_packages[nlos[0]].station.id}) reach the target only with "
                "ranges through the structure (NLOS, biased): more anchors in sight make "
                "them safer (remove the anchors to have them planned)",
            )
        )
    return rows
