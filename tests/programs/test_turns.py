"""The turn of A1 each chain of a program takes, settled over the whole program."""

from __future__ import annotations

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.programs.motion_checks import needless_swings
from fabflow.programs.turns import SWING_COST, TURNS, settle_a1_turns
from fabflow.robots import get_robot

ROBOT = get_robot("kuka_kr60_3")
HOME = np.radians([180.0, -110.0, 150.0, 0.0, 50.0, 0.0])


def _program(seed: int, chains: int) -> tuple[np.ndarray, list, np.ndarray, np.ndarray]:
    """Targets in chains of 1-3 (a PTP and linear moves), many straight behind the arm
    (A1 at +-180 deg, where both turns fit), some linear moves with samples."""
    rng = np.random.default_rng(seed)
    lo, hi = ROBOT.joint_limits[:, 0], ROBOT.joint_limits[:, 1]
    sizes = rng.integers(1, 4, chains)
    n = int(sizes.sum())
    q = rng.uniform(lo * 0.9, hi * 0.9, (n, 6))
    behind = rng.random(n) < 0.5
    q[behind, 0] = rng.choice([-1.0, 1.0], behind.sum()) * np.radians(rng.uniform(176, 180))
    ptp = np.zeros(n, dtype=bool)
    ptp[np.r_[0, np.cumsum(sizes)[:-1]]] = True
    # a chain keeps one side: its linear moves stay near its PTP target's A1
    chain = np.cumsum(ptp) - 1
    start = np.flatnonzero(ptp)
    q[:, 0] = np.clip(q[start[chain], 0] + np.where(ptp, 0.0, rng.normal(0, 0.02, n)), lo[0], hi[0])
    via = [None if p else np.vstack([q[k - 1], q[k]])[None].mean(axis=1) for k, p in enumerate(ptp)]
    through = ptp & (rng.random(n) < 0.1)
    through[0] = False
    return q, via, ptp, through


def _cost(q: np.ndarray, ptp: np.ndarray, through: np.ndarray) -> float:
    """The program's PTP swings and A1 travel from HOME to HOME (through HOME where marked)."""
    path = [HOME]
    for k in range(len(q)):
        if through[k]:
            path.append(HOME)
        path.append(q[k])
    path.append(HOME)
    path = np.array(path)
    swing = needless_swings(ROBOT, path[:-1], path[1:])
    # linear moves do not count as swings: they are followed as lines
    kinds = [True]
    for k in range(len(q)):
        if through[k]:
            kinds.append(True)
        kinds.append(bool(ptp[k]))
    kinds.append(True)
    swing &= np.array(kinds[1:])
    return float(SWING_COST * swing.sum() + np.abs(np.diff(path[:, 0])).sum())


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 5))
def test_the_turns_are_the_cheapest_of_all_and_the_poses_stay(seed: int, chains: int) -> None:
    q, via, ptp, through = _program(seed, chains)
    out, out_via = settle_a1_turns(ROBOT, q, via, ptp, HOME, through)
    # the same poses, every value within the limits, whole chains shifted by whole turns
    np.testing.assert_allclose(ROBOT.fk(out), ROBOT.fk(q), atol=1e-9)
    assert ROBOT.within_limits(out).all()
    shift = out[:, 0] - q[:, 0]
    np.testing.assert_allclose(shift / (2 * np.pi), np.round(shift / (2 * np.pi)), atol=1e-12)
    np.testing.assert_allclose(out[:, 1:], q[:, 1:])
    chain = np.cumsum(ptp) - 1
    for c in np.unique(chain):
        assert np.ptp(shift[chain == c]) < 1e-12
    for v, w, s in zip(via, out_via, shift, strict=True):
        if v is not None:
            np.testing.assert_allclose(w[:, 0], v[:, 0] + s)
    # no choice of turns is cheaper (all of them tried)
    start = np.flatnonzero(ptp)
    ends = np.r_[start[1:], len(q)]
    best = np.inf
    for turns in itertools.product(TURNS, repeat=len(start)):
        trial = q.copy()
        for s, e, t in zip(start, ends, turns, strict=True):
            trial[s:e, 0] += t
        if ROBOT.within_limits(trial).all():
            best = min(best, _cost(trial, ptp, through))
    assert _cost(out, ptp, through) <= best + 1e-9
    assert _cost(out, ptp, through) <= _cost(q, ptp, through) + 1e-9


def test_a_magazine_straight_behind_turns_to_the_side_of_the_place() -> None:
    # place left (A1 +60), magazine behind (+180), place right (-60), home (+180):
    # the greedy one-ahead choice picks the magazine at +180 and swings the long
    # way to the right; the whole program takes -180 once the right place follows
    place_left = np.radians([60.0, -60.0, 90.0, 0.0, 60.0, 0.0])
    magazine = np.radians([180.0, -100.0, 140.0, 0.0, 50.0, 0.0])
    place_right = np.radians([-60.0, -60.0, 90.0, 0.0, 60.0, 0.0])
    q = np.array([place_left, magazine, place_right, magazine, place_right])
    ptp = np.ones(5, dtype=bool)
    out, _ = settle_a1_turns(ROBOT, q, [None] * 5, ptp, HOME, np.zeros(5, dtype=bool))
    assert np.degrees(out[1, 0]) == 180.0 or np.degrees(out[3, 0]) == -180.0
    assert np.degrees(out[3, 0]) == -180.0  # between two places on the right
    assert _cost(out, ptp, np.zeros(5, bool)) < _cost(q, ptp, np.zeros(5, bool))
