"""Total station set-ups planned for a whole build, and the segment test behind every sight line."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import DATA, PROJECTS
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.design.elements import element_boxes, structure_timeline
from fabflow.design.generate import generate_elements
from fabflow.errors import LocalizationError
from fabflow.localize.prism_points import station_points
from fabflow.localize.setups import (
    MIN_SIGHT,
    InstrumentSetup,
    control_points,
    plan_setups,
)
from fabflow.localize.stationing import register_setup
from fabflow.positioning import boxes as boxes_module
from fabflow.positioning.boxes import Boxes, segments_clear, segments_inside
from fabflow.project import TotalStationSetup, load_project, parse_project
from fabflow.schema import PoseSpec
from fabflow.tasks.planner import plan_project
from fabflow.transforms.so3 import exp_so3


def _slab_span(
    p0: np.ndarray, p1: np.ndarray, T: np.ndarray, extents: np.ndarray
) -> tuple[float, float]:
    """Where one segment enters and leaves one box (``lo >= hi``: it misses), written
    plainly (the reference)."""
    a = T[:3, :3].T @ (p0 - T[:3, 3])
    b = T[:3, :3].T @ (p1 - T[:3, 3])
    lo, hi = 0.0, 1.0
    for k in range(3):
        d = b[k] - a[k]
        h = 0.5 * extents[k]
        if abs(d) < 1e-12:
            if abs(a[k]) > h:
                return 1.0, 0.0
            continue
        t0, t1 = sorted(((-h - a[k]) / d, (h - a[k]) / d))
        lo, hi = max(lo, t0), min(hi, t1)
    return lo, hi


def _slab_hit(p0: np.ndarray, p1: np.ndarray, T: np.ndarray, extents: np.ndarray) -> bool:
    lo, hi = _slab_span(p0, p1, T, extents)
    return lo < hi


def _random_scene(seed: int, n_boxes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Box poses and extents, and 50 segment starts and ends, drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    T = np.repeat(np.eye(4)[None], n_boxes, axis=0)
    T[:, :3, :3] = exp_so3(rng.normal(0.0, 1.0, (n_boxes, 3)))
    T[:, :3, 3] = rng.uniform(0.0, 6.0, (n_boxes, 3))
    extents = rng.uniform(0.05, 1.0, (n_boxes, 3))
    return T, extents, rng.uniform(-1.0, 7.0, (50, 3)), rng.uniform(-1.0, 7.0, (50, 3))


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_boxes=st.integers(1, 60),
    offset=st.sampled_from([0.0, -1234.5, 6.0e5]),
)
def test_segments_clear_matches_a_plain_slab_test(seed: int, n_boxes: int, offset: float) -> None:
    # the boxes are grouped by the grid cells of their centres: negative and far
    # coordinates (a site in a national grid) group as near ones do
    T, extents, starts, ends = _random_scene(seed, n_boxes)
    T[:, :3, 3] += offset
    starts, ends = starts + offset, ends + offset
    clear = segments_clear(starts, ends, Boxes(T, extents))
    reference = [
        not any(_slab_hit(s, e, T[k], extents[k]) for k in range(n_boxes))
        for s, e in zip(starts, ends, strict=True)
    ]
    assert clear.tolist() == reference
    # the boxes' groups are kept for the next call: the same answer from them, and
    # from boxes moved apart (new groups), and without the cache
    assert segments_clear(starts, ends, Boxes(T, extents)).tolist() == reference
    T[:, :3, 3] += 3.0
    moved = segments_clear(starts + 3.0, ends + 3.0, Boxes(T, extents))
    assert moved.tolist() == reference
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(boxes_module, "GROUPS_CACHED", 0)
        assert segments_clear(starts + 3.0, ends + 3.0, Boxes(T, extents)).tolist() == reference


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")
def test_a_box_off_the_map_does_not_hide_the_others() -> None:
    # a box at NaN takes part in nothing (numpy warns of it); the box the segment
    # crosses still blocks it
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[0, :3, 3] = (1.0, 0.0, 0.0)
    T[1, :3, 3] = np.nan
    extents = np.full((2, 3), 0.5)
    clear = segments_clear(
        np.array([[0.0, 0.0, 0.0]]), np.array([[2.0, 0.0, 0.0]]), Boxes(T, extents)
    )
    assert clear.tolist() == [False]


def _slab_length(p0: np.ndarray, p1: np.ndarray, T: np.ndarray, extents: np.ndarray) -> float:
    lo, hi = _slab_span(p0, p1, T, extents)
    return max(hi - lo, 0.0) * float(np.linalg.norm(p1 - p0))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_boxes=st.integers(1, 60))
def test_segments_inside_matches_a_plain_slab_length(seed: int, n_boxes: int) -> None:
    T, extents, starts, ends = _random_scene(seed, n_boxes)
    inside = segments_inside(starts, ends, Boxes(T, extents))
    reference = [
        sum(_slab_length(s, e, T[k], extents[k]) for k in range(n_boxes))
        for s, e in zip(starts, ends, strict=True)
    ]
    np.testing.assert_allclose(inside, reference, atol=1e-9)
    # a segment is clear exactly where no length of it lies inside
    clear = segments_clear(starts, ends, Boxes(T, extents))
    assert (clear == (inside == 0)).all()


@pytest.fixture(scope="module")
def cabin():
    project = load_project(PROJECTS / "cabin")
    ts = TotalStationSetup(procedure="three_point")
    loc = project.localization.model_copy(update={"method": "total_station", "total_station": ts})
    project = project.model_copy(update={"localization": loc})
    elements = generate_elements(project.elements, project.path)
    plan = plan_project(project, elements)
    return project, elements, plan


def _inside_any(points: np.ndarray, T: np.ndarray, extents: np.ndarray) -> np.ndarray:
    local = np.einsum("kji,mkj->mki", T[:, :3, :3], points[:, None] - T[None, :, :3, 3])
    return (np.abs(local) <= 0.5 * extents[None]).all(axis=2).any(axis=1)


def test_planned_setups_cover_every_package_in_build_order(cabin) -> None:
    project, elements, plan = cabin
    setups = plan_setups(project, plan, elements)
    covered = [k for s in setups for k in s.packages]
    assert covered == list(range(len(plan.work_packages)))
    timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    # every planned tripod stands off the structure and the parking places
    for s in setups:
        eye = s.T_world_instrument[:3, 3]
        lo, hi = project.localization.total_station.tripod_height
        assert lo - 1e-9 <= eye[2] <= hi + 1e-9
        T_box, extents = element_boxes(elements)
        assert not _inside_any(eye[None], T_box, extents + 0.5)[0]
        assert len(s.control_points) >= 3
    # the three-point prisms of every package are in sight: checked by sampling the
    # sight lines against the standing blocks, not by the planner's slab test
    for s in setups:
        eye = s.T_world_instrument[:3, 3]
        for k in s.packages:
            standing, _ = timeline[k]
            T_base = plan.work_packages[k].station.T_world_base(T_platform_base)
            pts = station_points(project, T_base, standing, sight_from=eye).points
            world = pts @ T_base[:3, :3].T + T_base[:3, 3]
            assert (np.linalg.norm(world - eye, axis=1) >= MIN_SIGHT).all()
            T_box, extents = element_boxes(standing)
            t = np.linspace(0.0, 1.0, 400)[1:-1]
            line = eye + t[:, None, None] * (world - eye)[None]
            assert not _inside_any(line.reshape(-1, 3), T_box, extents).any()


def test_a_given_instrument_that_cannot_see_names_the_field(cabin) -> None:
    project, elements, plan = cabin
    ts = project.localization.total_station.model_copy(
        update={"T_world_instrument": PoseSpec(xyz=(2.0, 1.6, 0.2))}  # inside, on the floor
    )
    loc = project.localization.model_copy(update={"total_station": ts})
    with pytest.raises(LocalizationError, match="T_world_instrument"):
        plan_setups(project.model_copy(update={"localization": loc}), plan, elements)


def test_max_range_bounds_every_sight_and_too_short_a_range_names_it(cabin) -> None:
    project, elements, plan = cabin
    timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    controls = control_points(project)

    def limited(max_range: float):
        ts = project.localization.total_station.model_copy(update={"max_range": max_range})
        loc = project.localization.model_copy(update={"total_station": ts})
        return project.model_copy(update={"localization": loc})

    setups = plan_setups(limited(10.0), plan, elements)
    assert [k for s in setups for k in s.packages] == list(range(len(plan.work_packages)))
    for s in setups:
        eye = s.T_world_instrument[:3, 3]
        assert all(np.linalg.norm(controls[c] - eye) <= 10.0 for c in s.control_points)
        for k in s.packages:
            T_base = plan.work_packages[k].station.T_world_base(T_platform_base)
            pts = station_points(project, T_base, timeline[k][0], sight_from=eye).points
            world = pts @ T_base[:3, :3].T + T_base[:3, 3]
            assert (np.linalg.norm(world - eye, axis=1) <= 10.0).all()
    with pytest.raises(LocalizationError, match="raise max_range"):
        plan_setups(limited(8.0), plan, elements)


def _setup(registration: str, eye: np.ndarray, ids: tuple[str, ...] = ()) -> InstrumentSetup:
    T = np.eye(4)
    T[:3, 3] = eye
    return InstrumentSetup("T1", T, (0,), registration, ids, 0.001)  # type: ignore[arg-type]


def test_free_stationing_covariance_matches_its_errors(cabin) -> None:
    """NEES of the registered set-up (x, y, z, yaw) over seeded draws: mean about 4."""
    project = cabin[0]
    controls = control_points(project)
    setup = _setup("control_points", np.array([6.0, 2.0, 1.6]), tuple(controls))
    rng = np.random.default_rng(7)
    nees = []
    sigma = project.localization.total_station.control_sigma_mm * 1e-3
    for _ in range(300):
        survey = {k: rng.normal(0.0, sigma, 3) for k in controls}
        pose = register_setup(project, setup, rng, survey)
        d = pose.T_est[:3, 3] - pose.T_true[:3, 3]
        yaw = np.arctan2(pose.T_est[1, 0], pose.T_est[0, 0])
        e = np.r_[d, yaw]
        C = pose.covariance[np.ix_([0, 1, 2, 5], [0, 1, 2, 5])]
        nees.append(float(e @ np.linalg.solve(C, e)))
    assert 3.4 < np.mean(nees) < 4.6


def test_procedure_a_inherits_the_robots_error(cabin) -> None:
    """A set-up registered on the robot's prisms carries the base estimate's error and
    covariance; on control points it does not."""
    project, _, plan = cabin
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    T_base = plan.work_packages[0].station.T_world_base(T_platform_base)
    offset = np.eye(4)
    offset[:3, 3] = [0.02, -0.01, 0.0]
    T_est = offset @ T_base
    C_base = np.diag([1e-4, 1e-4, 1e-4, 1e-6, 1e-6, 1e-5])
    eye = np.array([2.75, -2.75, 1.8])
    rng = np.random.default_rng(3)
    a = register_setup(project, _setup("robot_points", eye), rng, {}, (T_base, T_est, C_base))
    # the known prism positions are off by the base error: so is the new set-up
    assert np.allclose(a.T_est[:2, 3] - eye[:2], [0.02, -0.01], atol=0.003)
    assert a.covariance[0, 0] > C_base[0, 0] and a.covariance[1, 1] > C_base[1, 1]
    controls = control_points(project)
    b = register_setup(
        project,
        _setup("control_points", eye, tuple(controls)),
        rng,
        {k: np.zeros(3) for k in controls},
    )
    assert np.linalg.norm(b.T_est[:2, 3] - eye[:2]) < 0.003
    assert b.covariance[0, 0] < 0.1 * a.covariance[0, 0]


def test_set_ups_that_see_but_miss_the_accuracy_say_by_how_much() -> None:
    """Planned set-ups that see the prisms but predict more than 0.1 of the tolerance:
    the error gives the best predicted sigma and the remedies, not the line of sight."""
    text = (DATA / "sim" / "project.yaml").read_text()
    text = text.replace("  method: uwb\n", "  method: total_station\n", 1)
    text = text.replace(
        "localization:\n", "localization:\n  total_station: {prism_centring_mm: 3}\n", 1
    )
    project = parse_project(text)
    elements = generate_elements(project.elements, project.path)
    plan = plan_project(project, elements)
    with pytest.raises(LocalizationError, match=r"predicts \d+\.\d\d mm \(XY\).*prism_centring_mm"):
        plan_setups(project, plan, elements)
