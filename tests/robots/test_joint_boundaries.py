"""Configuration bits of joints on a boundary do not follow float noise."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.programs.writers.rapid import confdata
from fabflow.robots import get_robot, kuka_status_turn
from fabflow.robots.joint_boundaries import BOUNDARY_TOL_RAD, quadrants, settle_zeros

QUARTER = np.pi / 2
noise = st.floats(-1e-12, 1e-12, allow_nan=False)
joint = st.floats(-3.0, 3.0, allow_nan=False)


def configuration(
    values: list[float], on: list[bool], edges: list[int], jitter: list[float], step: float
) -> tuple[np.ndarray, np.ndarray]:
    """A configuration with some joints exactly on an edge, and the same with float noise."""
    exact = np.where(on, np.array(edges) * step, values)
    return exact, exact + np.where(on, jitter, 0.0)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(joint, min_size=6, max_size=6),
    st.lists(st.booleans(), min_size=6, max_size=6),
    st.lists(noise, min_size=6, max_size=6),
)
def test_kuka_bits_of_zero_joints_ignore_float_noise(
    values: list[float], on: list[bool], jitter: list[float]
) -> None:
    exact, noisy = configuration(values, on, [0] * 6, jitter, 1.0)
    assert kuka_status_turn(noisy) == kuka_status_turn(exact)


@settings(max_examples=150, deadline=None)
@given(
    st.lists(joint, min_size=6, max_size=6),
    st.lists(st.booleans(), min_size=6, max_size=6),
    st.lists(st.integers(-1, 1), min_size=6, max_size=6),
    st.lists(noise, min_size=6, max_size=6),
)
def test_abb_confdata_on_quadrant_edges_ignores_float_noise(
    values: list[float], on: list[bool], edges: list[int], jitter: list[float]
) -> None:
    robot = get_robot("abb_irb4600_60_205")
    exact, noisy = configuration(values, on, edges, jitter, QUARTER)
    exact[4] = 0.0 if on[4] else exact[4]  # axis 5 matters by its sign only
    noisy[4] = jitter[4] if on[4] else noisy[4]
    flange = robot.frames(exact)[robot.dof]
    assert confdata(noisy, flange, robot.opw) == confdata(exact, flange, robot.opw)


def test_turn_bit_of_a1_just_below_zero() -> None:
    """The case found in a cabin build: A1 = -1e-16 at the magazine's pick."""
    q = np.radians([0.0, -90.0, 90.0, 0.0, 10.0, 0.0])
    q[0] = -1e-16
    assert kuka_status_turn(q) == (2, 2)
    q[0] = -10 * BOUNDARY_TOL_RAD
    assert kuka_status_turn(q) == (2, 3)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-20.0, 20.0, allow_nan=False), min_size=1, max_size=8))
def test_quadrants_are_floor_away_from_edges(values: list[float]) -> None:
    q = np.array(values)
    t = q / QUARTER
    far = np.abs(t - np.round(t)) * QUARTER > BOUNDARY_TOL_RAD
    assert np.array_equal(quadrants(q)[far], np.floor(t[far]).astype(np.int64))
    near = ~far
    assert np.array_equal(quadrants(q)[near], np.round(t[near]).astype(np.int64))


def test_settle_zeros_keeps_other_values_and_signs() -> None:
    q = np.array([-1e-12, 1e-12, -2e-9, 2e-9, -0.0, 0.5])
    out = settle_zeros(q)
    assert np.array_equal(out, [0.0, 0.0, -2e-9, 2e-9, 0.0, 0.5])
    assert not np.signbit(out[:2]).any() and not np.signbit(out[4])
    assert q[0] == -1e-12  # the input is not changed


def test_a_joint_value_that_is_not_finite_has_no_quadrant() -> None:
    with pytest.raises(ValueError, match="not finite"):
        quadrants(np.array([0.1, np.nan]))
