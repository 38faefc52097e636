"""Total station set-ups for a whole build: where the instrument stands, and when it moves.

A robotic total station must see the prism the robot holds at every station,
through the structure as built at that visit. As the walls rise, one set-up
stops seeing into the building and the instrument moves, as in paper 001.

:func:`plan_setups` scores candidate positions on a grid over the site
(``setup_spacing``, at the lowest, middle and highest ``tripod_height``, clear of
the structure, the obstacles and the platform's parking places) against every
work package's prism points (:func:`fabflow.localize.prism_points.station_points`,
the points of eqs 9-11): a candidate covers a package when it sees every point
through the structure standing then, none closer than :data:`MIN_SIGHT` (nor
farther than ``max_range``, when the project limits it). In
build order, it keeps the set-up that covers the longest run of packages from
the first one not yet covered (the greedy choice is optimal for covering a
sequence with runs), the smallest predicted base position sigma among equals.
Each new set-up must also be registrable where it stands: on at least
:data:`MIN_CONTROL_POINTS` visible control points (free stationing, Procedure B
of paper 001), or, with ``stationing: robot_points`` (Procedure A), on the
prisms the robot holds at its last station of the set-up before.

:mod:`fabflow.localize.stationing` registers each set-up when it is put up.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from fabflow.design.elements import Element, element_boxes, structure_timeline
from fabflow.errors import LocalizationError
from fabflow.localize.prism_points import (
    THREE_POINT_ALTERNATIVES,
    instrument_for,
    station_points,
    total_station_setup,
)
from fabflow.localize.site import free_ground
from fabflow.positioning.boxes import Boxes, segments_clear
from fabflow.positioning.polar import cartesian_to_polar, polar_covariance
from fabflow.positioning.rigid_fit import point_jacobians
from fabflow.positioning.total_station import setup_covariance
from fabflow.project import Project, TotalStationSetup
from fabflow.tasks.plan import Plan
from fabflow.transforms.se3 import make_T

MIN_SIGHT = 2.0
"""Closest a sighted prism or control point may be to the instrument (metres): the
telescope's focus, and a tripod out of the arm's way."""
TRIPOD_CLEARANCE = 0.5
"""Distance (metres) a planned tripod keeps from the structure, obstacles and parking places."""
MIN_CONTROL_POINTS = 3
"""Control points a free stationing sights: two fix a levelled set-up, the third checks it."""
FOLLOWED = 512
"""Candidates followed through a run of packages: after its first package, those with
the smallest predicted sigma (the run of the best of them is kept)."""
CONTROL_HEIGHT = 0.3
"""Height of the default control points above the ground (metres)."""

Registration = Literal["given", "control_points", "robot_points"]


@dataclass(frozen=True, eq=False)
class InstrumentSetup:
    """One planned (or given) place of the instrument.

    Attributes
    ----------
    id
        ``"T1"``, ``"T2"``, ... in build order.
    T_world_instrument
        4x4 pose of the trunnion (world, metres; levelled, Hz zero along world y).
    packages
        Work package indices it localizes, in build order.
    registration
        ``"given"`` (the project's pose), ``"control_points"`` or ``"robot_points"``.
    control_points
        Ids of the control points it sights for free stationing.
    predicted_sigma
        Largest predicted base position sigma (XY, metres) over its packages.
    """

    id: str
    T_world_instrument: np.ndarray
    packages: tuple[int, ...]
    registration: Registration
    control_points: tuple[str, ...]
    predicted_sigma: float

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible data."""
        return {
            "id": self.id,
            "position": np.asarray(self.T_world_instrument[:3, 3], dtype=float).tolist(),
            "packages": [self.packages[0] + 1, self.packages[-1] + 1],
            "registration": self.registration,
            "control_points": list(self.control_points),
            "predicted_sigma_xy_mm": 1000.0 * self.predicted_sigma,
        }


def trunnion_pose(T_world_instrument: np.ndarray, instrument_height: float) -> np.ndarray:
    """The set-up pose raised by the instrument height along its z axis (4x4, metres)."""
    T = np.array(T_world_instrument, dtype=float)
    T[:3, 3] += T[:3, 2] * instrument_height
    return T


def instrument_covariance(setup: TotalStationSetup) -> np.ndarray:
    """6x6 covariance of the set-up pose from the project's set-up uncertainty fields."""
    return setup_covariance(setup.setup_sigma_mm, setup.setup_sigma_arcsec)


def control_points(project: Project) -> dict[str, np.ndarray]:
    """The control points by id (world, metres): the project's, or the site's corners."""
    given = total_station_setup(project).control_points
    if given:
        return {k: np.asarray(v, dtype=float) for k, v in given.items()}
    (x0, y0), (x1, y1) = project.site.extent_min, project.site.extent_max
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return {
        f"CP{i + 1}": np.array([x, y, CONTROL_HEIGHT], dtype=float)
        for i, (x, y) in enumerate(corners)
    }


def candidate_positions(project: Project, elements: Sequence[Element], plan: Plan) -> np.ndarray:
    """``(m, 3)`` candidate trunnion positions (world, metres) for planned set-ups: the
    free ground (:func:`~fabflow.localize.site.free_ground`, ``setup_spacing``) at the
    lowest, middle and highest ``tripod_height``."""
    setup = total_station_setup(project)
    xy = free_ground(project, elements, plan, setup.setup_spacing, TRIPOD_CLEARANCE)
    lo_h, hi_h = setup.tripod_height
    heights = np.unique([lo_h, 0.5 * (lo_h + hi_h), hi_h])
    return np.concatenate([np.column_stack([xy, np.full(len(xy), h)]) for h in heights])


def predicted_sigma(
    eyes: np.ndarray,
    points_world: np.ndarray,
    T_world_base: np.ndarray,
    project: Project,
    used: np.ndarray | None = None,
) -> np.ndarray:
    """Predicted XY position sigma of the base (metres) registered from each eye, ``(m,)``.

    The readings' first-order covariance (:func:`~fabflow.positioning.polar.polar_covariance`)
    plus the robot's repeatability, through the linearised 6-DOF registration
    ``p_world = Exp(r) R p_base + t + d``. ``used``: ``(m, n)`` which points each
    eye measures (default all); infinity where they do not fix the pose.
    """
    instrument = instrument_for(total_station_setup(project))
    local = points_world[None] - eyes[:, None]
    hz, v, sd = cartesian_to_polar(local)
    C = polar_covariance(hz, v, sd, instrument) + np.eye(3) * (
        project.simulation.robot_repeatability**2 + 1e-12
    )
    arm = points_world - np.asarray(T_world_base, dtype=float)[:3, 3]
    J = point_jacobians(np.eye(3), arm)
    W = np.linalg.inv(C)
    if used is not None:
        W = W * np.asarray(used, dtype=float)[..., None, None]
    info = (np.swapaxes(J, 1, 2)[None] @ (W @ J[None])).sum(axis=1)
    sigma = np.full(len(eyes), np.inf)
    fixed = np.linalg.cond(info) < 1e12
    cov = np.linalg.inv(info[fixed])
    sigma[fixed] = np.sqrt(cov[:, 0, 0] + cov[:, 1, 1])
    return sigma


SPARE_POINTS = 16
"""Spare clear prism positions per package that a set-up may sight instead of blocked ones."""
SIGMA_SHARE = 0.1
"""A set-up covers a package when its predicted base XY sigma is within this share of
``tolerances.position``."""


@dataclass(frozen=True)
class _Package:
    """What a set-up must see at one work package."""

    points: np.ndarray  # (n, 3) prism points, world
    spare: np.ndarray  # (k, 3) other clear prism positions, most spread first, world
    T_world_base: np.ndarray
    boxes: Boxes  # the structure standing, world
    alternatives: np.ndarray  # three_point: (a, 3, 3) other places of the three points, world


def _packages(
    project: Project, plan: Plan, standing: Sequence[Sequence[Element]]
) -> list[_Package]:
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    three_point = total_station_setup(project).procedure == "three_point"
    spare = THREE_POINT_ALTERNATIVES if three_point else SPARE_POINTS
    # every element's box once; each package's standing structure is a selection
    everything = {e.id: e for built in standing for e in built}
    ids = list(everything)
    row = {k: i for i, k in enumerate(ids)}
    T_box, extents = element_boxes([everything[k] for k in ids])
    boxed = np.full(len(ids), -1)
    has_box = [everything[k].extents is not None for k in ids]
    boxed[np.flatnonzero(has_box)] = np.arange(len(extents))
    out = []
    for wp, built in zip(plan.work_packages, standing, strict=True):
        sel = boxed[[row[e.id] for e in built]] if built else np.zeros(0, dtype=int)
        sel = sel[sel >= 0]
        boxes = Boxes(T_box[sel], extents[sel]) if len(sel) else Boxes.empty()
        T = wp.station.T_world_base(T_platform_base)
        pts = station_points(
            project, T, built, station_id=wp.station.id, spare=spare, boxes_world=boxes
        )
        world = pts.points @ T[:3, :3].T + T[:3, 3]
        pool = pts.spare @ T[:3, :3].T + T[:3, 3]
        alternatives = pts.alternatives @ T[:3, :3].T + T[:3, 3]
        out.append(_Package(world, pool, T, boxes, alternatives))
    return out


def _visible(
    eyes: np.ndarray, points: np.ndarray, boxes: Boxes, max_range: float | None = None
) -> np.ndarray:
    """``(m, n)`` which points each eye sees, none closer than :data:`MIN_SIGHT` nor
    farther than ``max_range`` (metres; ``None``: no limit)."""
    distance = np.linalg.norm(points[None] - eyes[:, None], axis=-1)
    visible = distance >= MIN_SIGHT
    if max_range is not None:
        visible &= distance <= max_range
    rows, cols = np.nonzero(visible)
    visible[rows, cols] = segments_clear(eyes[rows], points[cols], boxes)
    return visible


def _sighted(
    eyes: np.ndarray, package: _Package, max_range: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Which points each eye measures, ``(m, n + k)`` over the package's points then its
    spare ones: the visible points, blocked ones replaced by visible spare points, most
    spread first. ``three_point``: over its three points then the alternative places,
    the first place whose three points are all visible (what the localization chooses)."""
    if len(package.alternatives):
        sets = np.concatenate([package.points[None], package.alternatives])
        flat = sets.reshape(-1, 3)
        seen = _visible(eyes, flat, package.boxes, max_range).reshape(len(eyes), -1, 3)
        whole = seen.all(axis=2)
        first = np.where(whole.any(axis=1), np.argmax(whole, axis=1), -1)
        used = (np.arange(len(sets))[None, :] == first[:, None])[:, :, None] & seen
        return used.reshape(len(eyes), -1), flat
    n = len(package.points)
    used = np.zeros((len(eyes), n + len(package.spare)), dtype=bool)
    used[:, :n] = _visible(eyes, package.points, package.boxes, max_range)
    missing = n - used[:, :n].sum(axis=1)
    short = np.flatnonzero(missing > 0)
    if len(short) and len(package.spare):
        spare = _visible(eyes[short], package.spare, package.boxes, max_range)
        used[short, n:] = spare & (np.cumsum(spare, axis=1) <= missing[short, None])
    return used, np.concatenate([package.points, package.spare])


def _sigma(eyes: np.ndarray, package: _Package, project: Project) -> np.ndarray:
    """``(m,)`` predicted base XY sigma from each eye with the points it measures (metres;
    infinity with fewer than three)."""
    used, points = _sighted(eyes, package, total_station_setup(project).max_range)
    sigma = np.full(len(eyes), np.inf)
    ok = used.sum(axis=1) >= 3
    if ok.any():
        sigma[ok] = predicted_sigma(eyes[ok], points, package.T_world_base, project, used[ok])
    return sigma


def _covers(eyes: np.ndarray, package: _Package, project: Project) -> np.ndarray:
    """``(m,)`` which eyes localize the package: at least three points measured, the
    predicted XY sigma within :data:`SIGMA_SHARE` of the position tolerance."""
    return _sigma(eyes, package, project) <= SIGMA_SHARE * project.tolerances.position


def _sees_controls(
    eyes: np.ndarray, controls: np.ndarray, boxes: Boxes, max_range: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """``(m,)`` whether each eye sights enough control points, and ``(m, k)`` which."""
    seen = _visible(eyes, controls, boxes, max_range)
    return seen.sum(axis=1) >= min(MIN_CONTROL_POINTS, len(controls)), seen


def _earlier_handover(
    eyes: np.ndarray,
    packages: Sequence[_Package],
    previous: Sequence[int],
    i: int,
    project: Project,
) -> int | None:
    """The latest package ``j`` of the previous set-up's run (not its first) where a new
    set-up could take over on the robot's prisms: it sees package ``j - 1``'s and covers
    packages ``j`` to ``i``; None when there is none."""
    for j in range(i - 1, previous[0], -1):
        ok = _covers(eyes, packages[j - 1], project)
        for k in range(j, i + 1):
            if not ok.any():
                break
            idx = np.flatnonzero(ok)
            ok[idx] = _covers(eyes[idx], packages[k], project)
        if ok.any():
            return j
    return None


def plan_setups(
    project: Project,
    plan: Plan,
    elements: Sequence[Element],
    standing: Sequence[Sequence[Element]] | None = None,
) -> tuple[InstrumentSetup, ...]:
    """The instrument set-ups of a build (see the module docstring).

    With ``localization.total_station.T_world_instrument`` given, one set-up
    there, checked against every package.

    Parameters
    ----------
    project, plan, elements
        The project, its plan and all its elements (world frame).
    standing
        Per work package, the structure standing when it starts (default: the
        plan's timeline, :func:`~fabflow.design.elements.structure_timeline`).

    Raises
    ------
    LocalizationError
        Naming the first work package and station no set-up sees, and the
        field to change.
    """
    setup = total_station_setup(project)
    if standing is None:
        timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
        standing = [built for built, _ in timeline]
    packages = _packages(project, plan, standing)
    ids = [wp.station.id for wp in plan.work_packages]
    if not packages:
        return ()
    if setup.T_world_instrument is not None:
        T = trunnion_pose(setup.T_world_instrument.matrix(), setup.instrument_height)
        eye = T[None, :3, 3]
        sigmas = [float(_sigma(eye, package, project)[0]) for package in packages]
        limit = SIGMA_SHARE * project.tolerances.position
        for k, sigma_k in enumerate(sigmas):
            if sigma_k <= limit:
                continue
            if np.isfinite(sigma_k):
                raise LocalizationError(
                    f"the total station at localization.total_station.T_world_instrument "
                    f"localizes work package {k + 1} (station {ids[k]}) to a predicted "
                    f"{1e3 * sigma_k:.2f} mm (XY), more than {SIGMA_SHARE:g} of "
                    f"tolerances.position ({1e3 * limit:.2f} mm); measure more prism points "
                    "(n_points), use a more accurate instrument or prism, or move it closer"
                )
            raise LocalizationError(
                f"the total station at localization.total_station.T_world_instrument does "
                f"not see the prism points of work package {k + 1} (station {ids[k]}) "
                "through the structure built by then, or stands closer than "
                f"{MIN_SIGHT:g} m to them"
                + ("" if setup.max_range is None else f" or farther than {setup.max_range:g} m")
                + "; remove T_world_instrument to have the set-ups planned, or move it"
            )
        return (InstrumentSetup("T1", T, tuple(range(len(packages))), "given", (), max(sigmas)),)

    eyes = candidate_positions(project, elements, plan)
    controls = control_points(project)
    control_ids = list(controls)
    control_xyz = np.stack([controls[k] for k in control_ids])
    if len(eyes) == 0:
        raise LocalizationError(
            "no place on the site for the total station's tripod: every candidate lies on "
            "the structure, an obstacle or a parking place; enlarge site.extent_min/max"
        )
    limit = SIGMA_SHARE * project.tolerances.position
    out: list[InstrumentSetup] = []
    i = 0
    while i < len(packages):
        registration_on_robot = setup.stationing == "robot_points" and bool(out)
        if registration_on_robot:
            allowed = _covers(eyes, packages[i - 1], project)
            why = f"sees the robot's prisms at work package {i} (station {ids[i - 1]})"
        else:
            allowed, _ = _sees_controls(eyes, control_xyz, packages[i].boxes, setup.max_range)
            why = f"sights {MIN_CONTROL_POINTS} control points"
        alive = np.flatnonzero(allowed)
        worst = np.zeros(len(alive))  # the largest predicted sigma over the run so far
        end = i
        nearest = np.inf  # the best predicted sigma at package i, where none is within
        while end < len(packages) and len(alive):
            sigma = _sigma(eyes[alive], packages[end], project)
            ok = sigma <= limit
            if not ok.any():
                nearest = float(sigma.min()) if end == i else nearest
                break
            alive, worst, end = alive[ok], np.maximum(worst[ok], sigma[ok]), end + 1
            keep = np.argsort(worst, kind="stable")[:FOLLOWED]
            alive, worst = alive[keep], worst[keep]
        if end == i and registration_on_robot:
            handover = _earlier_handover(eyes, packages, out[-1].packages, i, project)
            if handover is not None:
                # the set-up before ends sooner, where a new one sees both sides
                last = out.pop()
                out.append(replace(last, packages=tuple(range(last.packages[0], handover))))
                i = handover
                continue
        if end == i and np.isfinite(nearest):
            raise LocalizationError(
                f"no total station set-up localizes work package {i + 1} (station {ids[i]}) "
                f"to {SIGMA_SHARE:g} of tolerances.position ({1e3 * limit:.2f} mm): the best of "
                f"those that see its prism points and {why.split(' ', 1)[1]} predicts "
                f"{1e3 * nearest:.2f} mm (XY); measure more prism points (n_points), use a more "
                "accurate instrument or prism (prism_centring_mm)"
                + (
                    ", or use stationing 'control_points' (free stationing on fixed points)"
                    if registration_on_robot
                    else ", or give control points closer to the work"
                )
            )
        if end == i:
            raise LocalizationError(
                f"no total station set-up on the site sees the prism points of work package "
                f"{i + 1} (station {ids[i]}) through the structure built by then and {why}"
                + (
                    "; use stationing 'control_points' (free stationing on fixed points)"
                    if registration_on_robot
                    else "; raise localization.total_station.tripod_height, give more "
                    "control_points"
                    + ("" if setup.max_range is None else ", raise max_range")
                    + ", or use fewer n_points"
                )
            )
        run = range(i, end)
        best = int(alive[int(np.argmin(worst))])
        T = make_T(np.eye(3), eyes[best])
        registration: Registration = "control_points"
        sighted: tuple[str, ...] = ()
        if registration_on_robot:
            registration = "robot_points"
        else:
            _, seen = _sees_controls(
                eyes[best][None], control_xyz, packages[i].boxes, setup.max_range
            )
            sighted = tuple(k for k, s in zip(control_ids, seen[0], strict=True) if s)
        out.append(
            InstrumentSetup(
                f"T{len(out) + 1}", T, tuple(run), registration, sighted, float(worst.min())
            )
        )
        i = end
    return tuple(out)


def planned_setups(
    project: Project, plan: Plan, elements: Sequence[Element], method: str | None = None
) -> tuple[InstrumentSetup, ...] | None:
    """The set-ups of a project localized by total station from simulated readings (given
    or planned, :func:`plan_setups`); ``None`` for the other methods and for measured
    readings. ``method``: instead of the project's."""
    method = method or project.localization.method
    if method != "total_station" or total_station_setup(project).observations is not None:
        return None
    return plan_setups(project, plan, elements)


def setups_document(project: Project, setups: Sequence[InstrumentSetup]) -> dict[str, Any]:
    """``instrument_setups.json``: the set-ups in build order and the control points."""
    ts = total_station_setup(project)
    return {
        "frame": "world",
        "units": "m",
        "stationing": ts.stationing,
        "control_points": {k: v.tolist() for k, v in control_points(project).items()},
        "setups": [s.to_dict() for s in setups],
    }


def setup_rows(setups: Sequence[InstrumentSetup]) -> list[tuple[str, str]]:
    """Build summary rows: how many set-ups, and when and where the instrument moves
    (none without set-ups)."""
    if not setups:
        return []
    rows = [("total station set-ups", str(len(setups)))]
    for s in setups:
        x, y, z = s.T_world_instrument[:3, 3]
        first, last = s.packages[0] + 1, s.packages[-1] + 1
        via = {"given": "as given", "control_points": "on " + ", ".join(s.control_points)}.get(
            s.registration, "on the robot's prisms"
        )
        rows.append(
            (
                f"set-up {s.id}",
                f"packages {first}-{last}: at ({x:.2f}, {y:.2f}), trunnion {z:.2f} m, "
                f"registered {via}; predicted XY sigma {1000 * s.predicted_sigma:.1f} mm",
            )
        )
    return rows
