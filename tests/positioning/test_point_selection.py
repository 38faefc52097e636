"""Total station point selection (eqs 9-11), obstacle avoidance, station simulator, procedures."""

from __future__ import annotations

import numpy as np
import pytest

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.boxes import Boxes, boxes_overlap, segments_hit
from fabflow.positioning.point_selection import (
    ClearanceRules,
    Workspace,
    avoid_obstacles,
    clear_mask,
    optimal_points,
    sample_workspace,
    sphere_grid,
    spread_objective,
)
from fabflow.transforms.se3 import make_T
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
