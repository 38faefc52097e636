"""Linear moves followed at once on one branch agree with following them one by one."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InfeasibleError
from fabflow.programs import feasibility
from fabflow.programs.branch_follow import (
    MAX_JOINT_STEP,
    MIN_SPEED_FRACTION,
    follow_branch,
    follow_branch_chain,
    nearest_prefix,
)
from fabflow.programs.motion_checks import wrap_angle, wrist_flips
from fabflow.programs.motions import Waypoint
from fabflow.robots import get_robot
from fabflow.transforms.so3 import exp_so3

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
        assert _same(got, follow_branch(ROBOT, q_branch[rows], ok[rows], q_prev, step))
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
    fast = follow_branch_chain(ROBOT, q, ok, counts, q_prev, dt)
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
    fast = follow_branch_chain(ROBOT, q, ok, counts, q_prev, np.full(3, 0.01))
    assert len(fast) == 2
    np.testing.assert_allclose(fast[1][0], q[2:4], atol=1e-12)


@st.composite
def lines(draw: st.DrawFn) -> tuple[np.ndarray, ...]:
    """A linear move of the KR 60-3's flange from a random configuration (sometimes
    near the wrist singularity or with A6 near a limit), solved at every sample
    with every branch; the branch numbers shuffled at some samples, as the
    closed-form solver swaps them."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    lo, hi = ROBOT.joint_limits[:, 0], ROBOT.joint_limits[:, 1]
    q0 = rng.uniform(0.8 * lo, 0.8 * hi)
    q0[4] = draw(st.sampled_from([q0[4], 0.02, -0.005]))
    q0[5] = draw(st.sampled_from([q0[5], hi[5] - 0.02, lo[5] + 0.02]))  # A6 at a limit
    m = draw(st.integers(1, 70))
    T0 = ROBOT.fk(q0)
    reach = rng.normal(size=3)
    reach *= draw(st.sampled_from([0.01, 0.1, 0.5])) / np.linalg.norm(reach)
    turn = rng.normal(0.0, draw(st.sampled_from([0.0, 0.05, 0.5])), 3)
    turn += T0[:3, 2] * draw(st.sampled_from([0.0, 0.3, -0.3]))  # A6 turning on
    frac = np.linspace(0.0, 1.0, m + 1)[1:]
    T = np.repeat(T0[None], m, axis=0)
    T[:, :3, 3] += frac[:, None] * reach
    T[:, :3, :3] = exp_so3(frac[:, None] * turn) @ T0[:3, :3]
    q_rows, valid = ROBOT.ik_batch(T)
    shuffled = rng.random(m) < draw(st.sampled_from([0.0, 0.1, 0.5]))
    order = np.tile(np.arange(q_rows.shape[1]), (m, 1))
    order[shuffled] = np.argsort(rng.random((int(shuffled.sum()), q_rows.shape[1])), axis=1)
    q_rows = np.take_along_axis(q_rows, order[:, :, None], axis=1)
    valid = np.take_along_axis(valid, order, axis=1)
    dt = draw(st.sampled_from([0.001, 0.01, 0.05, 0.3]))
    return q_rows, valid, q0, T, dt


def nearest_one_by_one(
    q_rows: np.ndarray, valid: np.ndarray, q_prev: np.ndarray, dt: float
) -> tuple[np.ndarray, int]:
    """The samples taken one by one, each the valid solution nearest the one before
    (multi-turn joints by the shortest angle), up to the first with no solution, a
    step over the speed limits or MAX_JOINT_STEP, or a path out of the limits."""
    path, branch = [], -1
    rate = ROBOT.velocity_limits * dt
    for q, ok in zip(q_rows, valid, strict=True):
        candidates = np.flatnonzero(ok)
        if len(candidates) == 0:
            break
        steps = q[candidates] - q_prev
        steps[:, MULTI_TURN] = wrap_angle(steps[:, MULTI_TURN])
        best = int(np.argmin((np.abs(steps) / rate).max(axis=1)))
        step = steps[best]
        if (np.abs(step) / rate).max() > 1.0 or np.abs(step).max() > MAX_JOINT_STEP:
            break
        if not ROBOT.within_limits(q_prev + step):
            break
        q_prev = q_prev + step
        path.append(q_prev)
        branch = int(candidates[best])
    return np.reshape(path, (-1, ROBOT.dof)), branch


@settings(max_examples=200, deadline=None)
@given(lines())
def test_the_nearest_prefix_is_the_samples_taken_one_by_one(case: tuple[np.ndarray, ...]) -> None:
    q_rows, valid, q0, _, dt = case
    path, branch = nearest_prefix(ROBOT, q_rows, valid, q0, dt)
    want, want_branch = nearest_one_by_one(q_rows, valid, q0, dt)
    assert len(path) == len(want)
    assert branch == want_branch
    np.testing.assert_allclose(path, want, rtol=0, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(lines())
def test_stepping_through_after_the_prefix_is_stepping_through_from_the_start(
    case: tuple[np.ndarray, ...],
) -> None:
    q_rows, valid, q0, T, dt = case
    wp = Waypoint("lin", np.eye(4), 0.1, 0.0, "descent", "B1")

    def step_through() -> tuple[np.ndarray, int, float] | str:
        try:
            return feasibility._step_through(ROBOT, wp, q_rows, valid, q0, T, T, dt)
        except InfeasibleError as error:
            return str(error)

    got = step_through()
    with pytest.MonkeyPatch.context() as patch:  # every sample by the loop, as before
        patch.setattr(feasibility, "nearest_prefix", lambda *a: (np.zeros((0, 6)), -1))
        want = step_through()
    if isinstance(want, str) or isinstance(got, str):
        assert got == want
        return
    np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-12)
    assert got[1:] == pytest.approx(want[1:], rel=1e-12)
