"""Total station point selection (eqs 9-11), obstacle avoidance, station simulator, procedures."""

from __future__ import annotations

import numpy as np
import pytest

from fabflow.design.elements import Element
from fabflow.errors import InputError, LocalizationError
from fabflow.localize.total_station import boxes_in_base, localize_station
from fabflow.positioning.point_selection import (
    Boxes,
    ClearanceRules,
    Workspace,
    avoid_obstacles,
    boxes_overlap,
    clear_mask,
    optimal_points,
    sample_workspace,
    segments_hit,
    sphere_grid,
    spread_objective,
)
from fabflow.project import parse_project
from fabflow.sensors.ts_procedures import simulate_procedures
from fabflow.transforms.se3 import apply_T, make_T, pose_error
from fabflow.transforms.so3 import exp_so3

PAPER = Workspace(center=(0.0, 0.0, 1.0), reach=2.55, margin=0.0, min_radius=0.0)


def wall(center: tuple[float, float, float], size: tuple[float, float, float]) -> Boxes:
    T = make_T(np.eye(3), center)
    return Boxes(T[None], np.asarray([size], dtype=float))


@pytest.mark.parametrize("n", [3, 4, 6])
def test_optimal_points_satisfy_eq11_and_beat_random(n: int) -> None:
    rng = np.random.default_rng(n)
    P = optimal_points(n, PAPER, rng)
    assert P.shape == (n, 3)
    r = np.linalg.norm(P - [0.0, 0.0, 1.0], axis=1)
    assert np.all(r <= 2.55 + 1e-6) and np.all(P[:, 0] > 0) and np.all(P[:, 2] > 0)
    best_random = max(spread_objective(sample_workspace(PAPER, n, rng)) for _ in range(200))
    assert spread_objective(P) > best_random
    # spread: the points sit on the boundary of the reach sphere
    np.testing.assert_allclose(r, 2.55, atol=1e-3)


def test_optimal_points_refuse_too_few() -> None:
    with pytest.raises(InputError, match="at least 3"):
        optimal_points(2, PAPER, np.random.default_rng(0))


def test_spread_objective_matches_eq10() -> None:
    P = np.random.default_rng(0).normal(size=(5, 3))
    direct = np.sum(P**2) + sum(
        np.sum((P[i] - P[j]) ** 2) for i in range(5) for j in range(i + 1, 5)
    )
    assert spread_objective(P) == pytest.approx(direct)


def test_box_overlap_and_segments() -> None:
    boxes = wall((2.0, 0.0, 1.0), (0.2, 2.0, 2.0))
    centers = np.array([[2.0, 0.0, 1.0], [2.3, 0.0, 1.0], [2.2, 0.0, 1.0], [2.0, 1.25, 1.0]])
    hit = boxes_overlap(centers, np.array([0.15, 0.15, 0.15]), boxes)
    np.testing.assert_array_equal(hit, [True, False, True, False])
    # rotated box: 45 degrees about z, the corner reaches further along x
    T = make_T(exp_so3([0, 0, np.pi / 4]), [0.0, 0.0, 0.0])
    rot = Boxes(T[None], np.array([[1.0, 1.0, 1.0]]))
    near_corner = np.array([[0.75, 0.0, 0.0], [0.9, 0.0, 0.0]])
    np.testing.assert_array_equal(
        boxes_overlap(near_corner, np.array([0.05, 0.05, 0.05]), rot), [True, False]
    )
    ends = np.array([[4.0, 0.0, 1.0], [4.0, 0.0, 4.0], [1.5, 0.0, 1.0]])
    np.testing.assert_array_equal(
        segments_hit(np.array([0.0, 0.0, 1.0]), ends, boxes), [True, False, False]
    )
    assert not boxes_overlap(centers, np.ones(3), Boxes.empty()).any()


def test_sphere_grid_is_unit_and_even() -> None:
    g = sphere_grid(200)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0)
    np.testing.assert_allclose(g.mean(axis=0), 0.0, atol=0.02)


def test_avoid_obstacles_moves_blocked_points_only() -> None:
    ws = Workspace(center=(0.0, 0.0, 1.0), reach=2.55, margin=0.1)
    desired = np.array([[1.8, 0.0, 1.0], [0.5, 1.8, 1.2], [0.6, -1.8, 0.8]])
    boxes = wall((1.8, 0.0, 1.0), (0.3, 0.8, 0.8))  # the structure sits on the first point
    rules = ClearanceRules(tool_half_extents=(0.1, 0.1, 0.1))
    clear = avoid_obstacles(desired, ws, boxes, rules)
    out, moved = clear.points, clear.moved
    np.testing.assert_array_equal(clear.index, [0, 1, 2])
    assert moved[0] > 0 and np.all(moved[1:] == 0)
    np.testing.assert_allclose(moved[0] / 0.1, np.round(moved[0] / 0.1))
    np.testing.assert_allclose(np.linalg.norm(out[0] - desired[0]), moved[0])
    assert clear_mask(out, ws, boxes, rules).all()
    np.testing.assert_array_equal(out[1:], desired[1:])


def test_avoid_obstacles_respects_line_of_sight_and_gives_up() -> None:
    ws = Workspace(center=(0.0, 0.0, 1.0), reach=2.55, margin=0.1)
    desired = np.array([[1.5, 0.0, 1.0]])
    screen = wall((3.0, 0.0, 1.0), (0.1, 1.0, 1.0))
    rules = ClearanceRules(sight_from=(8.0, 0.0, 1.0))
    clear = avoid_obstacles(desired, ws, screen, rules)
    assert clear.moved[0] > 0
    assert not segments_hit(np.array([8.0, 0.0, 1.0]), clear.points, screen)[0]
    everything = wall((1.0, 0.0, 1.0), (8.0, 8.0, 8.0))
    with pytest.raises(LocalizationError, match=r"found only 0 of the 1 .* structure \d+"):
        avoid_obstacles(desired, ws, everything, rules, max_radius=0.3)


def test_avoid_obstacles_refills_hopeless_points_from_the_workspace() -> None:
    ws = Workspace(center=(0.0, 0.0, 1.0), reach=2.55, margin=0.1)
    desired = np.array([[1.5, 0.0, 1.0], [0.5, 1.8, 1.2], [0.6, -1.8, 0.8], [0.3, 0.0, 2.9]])
    # a screen hides the first point from the instrument with no way around within 0.3 m
    screen = wall((3.0, 0.0, 1.0), (0.1, 1.0, 1.0))
    rules = ClearanceRules(sight_from=(8.0, 0.0, 1.0))
    clear = avoid_obstacles(desired, ws, screen, rules, max_radius=0.3, min_points=3)
    assert sorted(clear.index.tolist()) == [0, 1, 2, 3] and clear.dropped == ()
    k = int(np.flatnonzero(clear.index == 0)[0])
    assert clear.moved[k] > 0.3
    assert clear_mask(clear.points, ws, screen, rules).all()
    assert not segments_hit(np.array([8.0, 0.0, 1.0]), clear.points, screen).any()


def test_boxes_in_base_frame() -> None:
    T_world_base = make_T(exp_so3([0, 0, np.pi / 2]), [5.0, 0.0, 0.5])
    block = Element(
        "B1", "block", make_T(np.eye(3), [5.0, 2.0, 0.5]), extents=np.array([0.6, 0.1, 0.1])
    )
    point = Element("T1", "task_point", np.eye(4))
    boxes = boxes_in_base([block, point], T_world_base)
    assert len(boxes) == 1
    np.testing.assert_allclose(boxes.T_base_box[0, :3, 3], [2.0, 0.0, 0.0], atol=1e-12)


PROJECT = """
name: ts
elements:
  - task_points:
      - id: a
        pose: {xyz: [1, 0, 0]}
localization:
  method: total_station
  total_station:
    T_world_instrument: {xyz: [-6, -4, 1.6]}
    n_points: 5
"""


def test_localize_station_simulates_a_plausible_pose() -> None:
    p = parse_project(PROJECT)
    rng = np.random.default_rng(0)
    T = make_T(exp_so3([0.0, 0.0, 0.7]), [2.0, 1.0, 0.6])
    bp = localize_station(p, T, rng, "S1")
    assert bp.method == "total_station" and bp.station == "S1"
    err = pose_error(bp.T_world_base, T)
    nees = err @ np.linalg.solve(bp.covariance, err)
    assert nees < 30  # chi2(6) 0.9999 quantile is about 27
    assert np.linalg.norm(err[:3]) < 0.005
    assert bp.residuals.shape == (5, 3) and bp.quality["n_points"] == 5
    P = np.asarray(bp.quality["points_base"])
    assert np.all(P[:, 0] > 0) and np.all(P[:, 2] > 0.1)
    again = localize_station(p, T, np.random.default_rng(0), "S1")
    np.testing.assert_array_equal(again.T_world_base, bp.T_world_base)


def test_localize_station_three_point_and_obstacles() -> None:
    p = parse_project(PROJECT.replace("n_points: 5", "procedure: three_point"))
    T = make_T(np.eye(3), [0.0, 0.0, 0.6])
    bp = localize_station(p, T, np.random.default_rng(1), "S1")
    assert bp.quality["solver"] == "three_point" and bp.residuals.shape == (3, 3)
    assert np.linalg.norm(pose_error(bp.T_world_base, T)[:3]) < 0.01
    # a block right where an optimal point wants to be pushes it away
    p5 = parse_project(PROJECT)
    free = localize_station(p5, T, np.random.default_rng(1), "S1")
    first = apply_T(T, np.asarray(free.quality["points_base"])[0])
    block = Element("B", "block", make_T(np.eye(3), first), extents=np.array([0.6, 0.3, 0.3]))
    blocked = localize_station(p5, T, np.random.default_rng(1), "S1", built=[block])
    assert blocked.quality["moved_for_obstacles"][0] > 0
    P = np.asarray(blocked.quality["points_base"])
    boxes = boxes_in_base([block], T)
    assert not boxes_overlap(P, np.array([0.15, 0.15, 0.2]), boxes).any()


def test_procedure_a_error_grows_and_b_does_not() -> None:
    study = simulate_procedures(np.random.default_rng(0), n_cycles=4, n_runs=300)
    a = study.deviation_a.mean(axis=0)
    b = study.deviation_b.mean(axis=0)
    assert np.all(np.diff(a) > 0)
    assert a[-1] > 2.5 * a[0]
    assert b.max() < 1.5 * b.min()
    assert a[-1] > 3 * b[-1]
    rows = study.table()
    assert len(rows) == 4 and rows[0][0] == 1


def test_instrument_setup_uncertainty_propagates() -> None:
    from fabflow.positioning.registration import register_points
    from fabflow.positioning.total_station import add_instrument_uncertainty

    # a heading error a of an instrument 10 m away moves the base sideways by 10 a
    T_wi = make_T(np.eye(3), [0.0, -10.0, 1.6])
    T_base = make_T(np.eye(3), [0.0, 0.0, 0.6])
    P = np.array([[1.0, 0.5, 0.5], [1.5, -0.5, 1.0], [0.5, 1.0, 1.5], [2.0, 0.0, 0.8]])
    reg = register_points(P, apply_T(T_base, P), sigma=1e-6)
    a = 1e-4
    C_wi = np.diag([0.0, 0.0, 0.0, 0.0, 0.0, a * a])
    out = add_instrument_uncertainty(reg, T_wi, C_wi)
    extra = out.covariance - reg.covariance
    assert np.sqrt(extra[0, 0]) == pytest.approx(10.0 * a, rel=1e-6)
    assert extra[1, 1] == pytest.approx(0.0, abs=1e-15)
    assert np.sqrt(extra[5, 5]) == pytest.approx(a)
    setup = "setup_sigma_mm: 3\n    setup_sigma_arcsec: 10"
    p = parse_project(PROJECT.replace("n_points: 5", setup))
    bp = localize_station(p, T_base, np.random.default_rng(2), "S1")
    assert np.sqrt(bp.covariance[2, 2]) > 3e-3
    err = pose_error(bp.T_world_base, T_base)
    assert err @ np.linalg.solve(bp.covariance, err) < 30


@pytest.mark.parametrize("model", ["ur10e", "brokk_170"])
def test_localize_station_other_robots(model: str) -> None:
    # the UR10e has closed-form IK; the 5-DOF BROKK reaches points by sampled FK
    p = parse_project(PROJECT.replace("elements:", f"robot: {{model: {model}}}\nelements:"))
    T = make_T(np.eye(3), [1.0, 2.0, 0.6])
    bp = localize_station(p, T, np.random.default_rng(3), "S1")
    P = np.asarray(bp.quality["points_base"])
    assert len(P) == 5 and np.all(P[:, 0] > 0)
    assert np.linalg.norm(pose_error(bp.T_world_base, T)[:3]) < 0.005
