"""RobotModel.nearest_turn gives exactly the nearest turn within limits of those it tries."""

from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.robots import get_robot

TWO_PI = 2.0 * np.pi


def every_turn(q: np.ndarray, ref: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Of the turns k0, k0 - 1, k0 + 1, k0 - 2, k0 + 2 (k0 nearest the reference) within
    limits, the first nearest the reference; k0 when none is within limits."""
    q, ref, lo, hi = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (q, ref, lo, hi)))
    k0 = np.round((ref - q) / TWO_PI)
    turns = np.array([0.0, -1.0, 1.0, -2.0, 2.0]).reshape(-1, *([1] * q.ndim))
    cand = q + (k0 + turns) * TWO_PI
    within = (cand >= lo - 1e-9) & (cand <= hi + 1e-9)
    first_nearest = np.argmin(np.where(within, np.abs(cand - ref), np.inf), axis=0)
    chosen = np.take_along_axis(cand, first_nearest[None], axis=0)[0]
    return np.where(within.any(axis=0), chosen, q + k0 * TWO_PI)


@settings(deadline=None, max_examples=60)
@given(
    seed=st.integers(0, 2**31),
    wide=st.booleans(),
    per_row_ref=st.booleans(),
    ties=st.booleans(),
)
def test_nearest_turn_equals_the_search_over_every_turn(
    seed: int, wide: bool, per_row_ref: bool, ties: bool
) -> None:
    rng = np.random.default_rng(seed)
    robot = get_robot("kuka_kr60_3")
    if wide:  # axes that turn more than once, as axis 6 of many arms
        limits = np.tile([-2.5 * TWO_PI, 2.5 * TWO_PI], (6, 1)) * rng.uniform(0.1, 1.0, (6, 1))
        robot = dataclasses.replace(robot, joint_limits=limits)
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    q = rng.uniform(-3.0 * TWO_PI, 3.0 * TWO_PI, (50, 8, 6))
    q[rng.random(q.shape) < 0.05] = np.nan  # branches that do not exist
    ref = rng.uniform(-TWO_PI, TWO_PI, (50, 1, 6) if per_row_ref else (6,))
    if ties:  # joint values half a turn from the reference, where two turns tie
        q = np.broadcast_to(ref, q.shape) + np.pi * rng.choice([-1.0, 1.0], q.shape)
    got = robot.nearest_turn(q, ref)
    np.testing.assert_array_equal(got, every_turn(q, ref, lo, hi))
    # one value and one reference for every joint: broadcast over the joints
    one = robot.nearest_turn(q[0, 0, 0], ref.ravel()[0])
    np.testing.assert_array_equal(one, every_turn(q[0, 0, 0], ref.ravel()[0], lo, hi))


def test_multi_turn_joints_are_those_with_more_than_a_turn_of_range() -> None:
    kuka = get_robot("kuka_kr60_3")  # A1 +-185, A4 and A6 +-350 deg
    assert kuka.multi_turn.tolist() == [True, False, False, True, False, True]
    ur = get_robot("ur10e")  # every joint +-360 deg
    assert ur.multi_turn.all()
