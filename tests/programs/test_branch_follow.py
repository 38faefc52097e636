"""Linear moves followed at once on one branch agree with following them one by one."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.programs.branch_follow import (
    MAX_JOINT_STEP,
    MIN_SPEED_FRACTION,
    follow_branch,
    follow_branch_chain,
)
from fabflow.programs.motion_checks import wrap_angle, wrist_flips
from fabflow.robots import get_robot

ROBOT = get_robot("kuka_kr60_3")
MULTI_TURN = np.diff(ROBOT.joint_limits, axis=1)[:, 0] > 2.0 * np.pi


def follow_one(
    q_branch: np.ndarray, ok: np.ndarray, q_prev: np.ndarray, dt: float
) -> tuple[np.ndarray, float] | None:
    """One move on one branch, written out: every sample valid, no joint step over
    MAX_JOINT_STEP, the slowdown its speeds need within 1 / MIN_SPEED_FRACTION,
    the path within the limits."""
    if not ok.all():
        return None
    steps = np.diff(np.vstack([q_prev, q_branch]), axis=0)
    steps[:, MULTI_TURN] = wrap_angle(steps[:, MULTI_TURN])
    if np.abs(steps).max() > MAX_JOINT_STEP:
        return None
    slowdown = max(1.0, float((np.abs(steps) / (ROBOT.velocity_limits * dt)).max()))
    if slowdown > 1.0 / MIN_SPEED_FRACTION:
        return None
    path = q_prev + np.cumsum(steps, axis=0)
    return (path, slowdown) if ROBOT.within_limits(path).all() else None


def one_by_one(
    q_branch: np.ndarray, ok: np.ndarray, counts: np.ndarray, q_prev: np.ndarray, dt: np.ndarray
) -> list[tuple[np.ndarray, float]]:
    """The moves followed in turn, up to the first refused or flipping one."""
    out = []
    first = np.r_[0, np.cumsum(counts)[:-1]]
    for start, count, step in zip(first, counts, dt, strict=True):
        rows = slice(start, start + count)
        got = follow_one(q_branch[rows], ok[rows], q_prev, float(step))
        assert _same(got, follow_branch(ROBOT, q_branch[rows], ok[rows], q_prev, MULTI_TURN, step))
        if got is None or wrist_flips(np.vstack([q_prev, got[0]])):
            break
        out.append(got)
        q_prev = got[0][-1]
    return out


def _same(a: tuple[np.ndarray, float] | None, b: tuple[np.ndarray, float] | None) -> bool:
    """Both refused, or the same path and slowdown."""
    if a is None or b is None:
        return a is b
    return bool(np.array_equal(a[0], b[0]) and a[1] == b[1])


@st.composite
def chains(draw: st.DrawFn) -> tuple[np.ndarray, ...]:
    """A joint path wandering by small steps, with sometimes a jump, an invalid sample,
    a fast stretch, a joint pushed past its limit or A5 crossing zero."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    counts = rng.integers(1, 5, size=draw(st.integers(1, 12)))
    m = int(counts.sum())
    q_prev = rng.uniform(-1.0, 1.0, 6)
    q_prev[4] = draw(st.sampled_from([0.5, -0.5, 0.002, 0.0]))
    steps = rng.normal(0.0, draw(st.sampled_from([1e-4, 3e-3, 0.02])), (m, 6))
    q = q_prev + np.cumsum(steps, axis=0)
    ok = np.ones(m, dtype=bool)
    event = draw(st.sampled_from(["none", "jump", "invalid", "limit", "turn", "a5"]))
    j = int(rng.integers(0, m))
    if event == "jump":
        q[j:, 1] += 2.0
    elif event == "invalid":
        ok[j] = False
        q[j] = np.nan
    elif event == "limit":
        q[j:, 2] = ROBOT.joint_limits[2, 1] + 0.01
    elif event == "turn":  # a multi-turn joint's solution given a whole turn away
        q[j, 5] += 2.0 * np.pi
    elif event == "a5":
        q[j:, 4] = -q_prev[4] if q_prev[4] else 0.01
    dt = rng.uniform(0.004, 0.05, len(counts))
    return q, ok, counts, q_prev, dt


@settings(max_examples=300, deadline=None)
@given(chains())
def test_chain_equals_moves_one_by_one(case: tuple[np.ndarray, ...]) -> None:
    q, ok, counts, q_prev, dt = case
    fast = follow_branch_chain(ROBOT, q, ok, counts, q_prev, MULTI_TURN, dt)
    slow = one_by_one(q, ok, counts, q_prev, dt)
    assert len(fast) == len(slow)
    for (path_f, slow_f), (path_s, slow_s) in zip(fast, slow, strict=True):
        np.testing.assert_allclose(path_f, path_s, rtol=0, atol=1e-12)
        assert slow_f == pytest.approx(slow_s, rel=1e-12)


def test_chain_stops_before_a_refused_move() -> None:
    q_prev = np.radians([0.0, -90.0, 90.0, 0.0, 30.0, 0.0])
    q = q_prev + np.radians(0.1) * np.arange(1, 7)[:, None]
    ok = np.ones(6, dtype=bool)
    ok[4] = False  # the third move's first sample
    counts = np.array([2, 2, 2])
    fast = follow_branch_chain(ROBOT, q, ok, counts, q_prev, MULTI_TURN, np.full(3, 0.01))
    assert len(fast) == 2
    np.testing.assert_allclose(fast[1][0], q[2:4], atol=1e-12)
