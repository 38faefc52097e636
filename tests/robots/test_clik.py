"""CLIK controller of paper 004: convergence, steps, damping, joint limits, phases, hydraulics."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError, UnsupportedError
from fabflow.robots import (
    Clik,
    ClikGains,
    HydraulicJoints,
    contact_search,
    divide_path,
    get_robot,
    tracking_rmse,
)
from fabflow.robots.hydraulic import reference_times


def deg(*a: float) -> np.ndarray:
    return np.radians(np.array(a, dtype=float))


@pytest.mark.parametrize("name", ["kuka_kr60_3", "abb_irb4600_60_205", "ur10e"])
def test_ptp_converges_to_reachable_pose(name: str) -> None:
    r = get_robot(name)
    c = Clik(r, "pose")
    q0 = r.q_nominal
    rng = np.random.default_rng(0)
    q_goal = q0 + rng.uniform(-0.4, 0.4, 6)
    goal = r.fk(q_goal)
    res = c.ptp(q0, goal, tol_position=1e-8, tol_rotation=1e-8)
    assert res.converged
    T = r.fk(res.q[-1])
    assert np.linalg.norm(T[:3, 3] - goal[:3, 3]) < 1e-8
    # Each iteration moves the flange by at most one 2 cm step (plus the closed error).
    p = r.fk(res.q)[:, :3, 3]
    assert np.linalg.norm(np.diff(p, axis=0), axis=1).max() < 0.0201
    assert r.within_limits(res.q).all()


def test_ptp_paper_thresholds_stop_within_one_step() -> None:
    r = get_robot("kuka_kr60_3")
    c = Clik(r, "pose")
    goal = r.fk(r.q_nominal)
    goal[:3, 3] += [0.0, 0.5, -0.3]
    res = c.ptp(r.q_nominal, goal)
    assert res.converged
    assert res.error_position <= 0.02 and res.error_rotation <= 0.015
    # 0.58 m in 2 cm steps: about 29 iterations, not many more.
    assert 25 <= res.iterations <= 35


def test_damping_is_zero_when_well_conditioned_and_grows_near_singularity() -> None:
    r = get_robot("kuka_kr60_3")
    c = Clik(r, "pose")
    _, J = c.measure(r.q_nominal)
    assert c.damping(J) == 0.0
    _, Js = c.measure(deg(0, -90, 90, 0, 0, 0))  # A5 = 0: wrist singular
    assert c.manipulability(Js) < 1e-12
    assert c.damping(Js) == pytest.approx(c.gains.k_damping)


def test_singular_start_does_not_blow_up() -> None:
    r = get_robot("kuka_kr60_3")
    c = Clik(r, "pose")
    q0 = deg(0, -90, 90, 0, 0, 0)
    goal = r.fk(deg(5, -85, 95, 20, 15, -10))
    res = c.ptp(q0, goal, tol_position=1e-6, tol_rotation=1e-6)
    assert np.isfinite(res.q).all()
    assert np.abs(np.diff(res.q, axis=0)).max() <= c.gains.max_joint_step + 1e-12
    assert res.converged


def test_unreachable_goal_degrades_gracefully() -> None:
    r = get_robot("kuka_kr60_3")
    c = Clik(r, "position", ClikGains(max_iter=400))
    goal = np.array([3.5, 0.0, 1.2])  # far beyond the 2.2 m reach
    res = c.ptp(r.q_nominal, goal, tol_position=1e-6)
    assert not res.converged
    assert np.isfinite(res.q).all()
    assert np.abs(np.diff(res.q, axis=0)).max() <= c.gains.max_joint_step + 1e-12
    assert r.within_limits(res.q).all()
    p = r.fk(res.q[-1])[:3, 3]
    # Stretched towards the goal: the remaining error is about the distance beyond reach.
    assert np.linalg.norm(p) > 1.9
    assert res.error_position < 3.5 - 1.9


def test_joint_limits_respected_and_weighted() -> None:
    r = get_robot("kuka_kr60_3")
    c = Clik(r, "position", ClikGains(max_iter=300))
    q0 = deg(0, -90, 90, 0, 45, 0)
    res = c.ptp(q0, np.array([0.2, 0.0, 3.5]), tol_position=1e-6)  # above reach: pulls A2/A3
    assert r.within_limits(res.q).all()
    c.reset()
    lo, hi = r.joint_limits[:, 0], r.joint_limits[:, 1]
    q_near = hi - 0.05 * (hi - lo)
    c.weights(q_near - 0.01)
    w_towards = c.weights(q_near)
    assert np.all(w_towards > 1.0)
    w_away = c.weights(q_near - 0.02)
    np.testing.assert_array_equal(w_away, 1.0)


def test_wln_penalises_joint_near_limit() -> None:
    r = get_robot("brokk_170")
    c = Clik(r, "position_pitch")
    _, J = c.measure(r.q_nominal)
    w = np.array([1.0, 1.0, 1.0, 1.0, 50.0])
    dx = np.array([0.01, 0.0, 0.01, 0.0])
    dq_free = c.pinv(J, np.ones(5), 0.0) @ dx
    dq_w = c.pinv(J, w, 0.0) @ dx
    assert abs(dq_w[4]) < abs(dq_free[4])
    np.testing.assert_allclose(J @ dq_w, dx, atol=1e-12)  # still an exact solution


def test_brokk_phased_ptp_moves_joint_2_alone() -> None:
    r = get_robot("brokk_170")
    c = Clik(r, "position_pitch")
    q0 = r.q_nominal
    x0, _ = c.measure(q0)
    goal = x0 + np.array([-0.7, 0.0, -0.7, 0.87])  # the paper's experiment 1 goal
    res = c.ptp_phased(q0, goal)
    assert res.converged
    moving = np.abs(np.diff(res.q, axis=0)) > 1e-12
    assert not np.any(moving[:, 1] & moving[:, [0, 2, 3, 4]].any(axis=1))
    assert set(np.unique(res.phase)) == {0, 1, 2}
    assert np.abs(np.diff(res.q, axis=0))[:, 1].max() <= c.gains.step_rotation + 1e-12
    assert r.within_limits(res.q).all()


def test_task_validation() -> None:
    with pytest.raises(UnsupportedError):
        Clik(get_robot("kuka_kr60_3"), "position_pitch")
    c = Clik(get_robot("kuka_kr60_3"), "pose")
    with pytest.raises(InputError):
        c.ptp(np.zeros(6), np.zeros(3))


def test_divide_path_at_4cm() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.5, 0.0]])
    W = divide_path(pts, 0.04)
    d = np.linalg.norm(np.diff(W, axis=0), axis=1)
    assert W.shape[0] == 39  # 1.5 m / 4 cm = 37.5 -> 38 intervals
    np.testing.assert_allclose(W[0], pts[0])
    np.testing.assert_allclose(W[-1], pts[-1])
    assert d[:-1].max() <= 0.04 + 1e-12
    with pytest.raises(InputError):
        divide_path(pts, 0.0)


def brokk_path() -> tuple[Clik, np.ndarray, np.ndarray]:
    r = get_robot("brokk_170")
    c = Clik(r, "position")
    q0 = r.q_nominal
    p0 = r.fk(q0)[:3, 3]
    pts = p0 + np.array([[0.0, 0.0, 0.0], [0.4, 0.3, 0.0], [0.4, 0.7, -0.3]])
    return c, q0, divide_path(pts, 0.04)


def test_track_path_kinematic_and_hydraulic() -> None:
    c, q0, W = brokk_path()
    r = c.robot
    res = c.track(q0, W)
    assert res.converged
    p = r.fk(res.q)[:, :3, 3]
    # The kinematic reference follows each 4 cm waypoint closely.
    np.testing.assert_allclose(p[1 : len(W)], W[1:], atol=2e-3)
    t_ref = reference_times(r, res.q, rate=2.0)
    kin = tracking_rmse(r, t_ref, res.q, t_ref, res.q)
    assert kin.rmse < 1e-12
    hyd = HydraulicJoints.for_robot(r)
    t, q = hyd.simulate(t_ref, res.q, t_extra=40.0)
    err = tracking_rmse(r, t, q, t_ref, res.q)
    # The 1.3 s dead time makes the machine lag: centimetres, not millimetres, and bounded.
    assert 0.01 < err.rmse < 0.5
    assert err.path_rmse < err.rmse
    assert np.linalg.norm(r.fk(q[-1])[:3, 3] - W[-1]) < 0.01  # settles at the end


def test_hydraulic_step_response_has_dead_time() -> None:
    r = get_robot("brokk_170")
    hyd = HydraulicJoints.for_robot(r)
    q0 = r.q_nominal
    q1 = q0.copy()
    q1[2] += 0.2  # the paper's 0.2 rad steps
    t_ref = np.array([0.0, 0.01])
    t, q = hyd.simulate(t_ref, np.vstack([q0, q1]), t_extra=40.0)
    moved = np.abs(q[:, 2] - q0[2]) > 1e-9
    assert t[np.argmax(moved)] >= 1.3 - 1e-9
    assert abs(q[-1, 2] - q1[2]) < 0.01
    assert np.max(q[:, 2] - q0[2]) < 0.2 * 1.6  # overshoot bounded (stable loop)
    np.testing.assert_allclose(q[:, [0, 1, 3, 4]], np.broadcast_to(q0[[0, 1, 3, 4]], (len(t), 4)))


def test_contact_search_finds_surface_and_hole() -> None:
    r = get_robot("brokk_170")
    c = Clik(r, "position")
    q0 = r.q_nominal
    p0 = r.fk(q0)[:3, 3]
    z_surf = p0[2] - 0.25
    res = contact_search(c, q0, lambda xy: z_surf, max_travel=1.0)
    assert res.contact
    assert abs(res.p_tcp[2] - z_surf) < 1e-6
    assert res.pressure[-1] > 40.0 and np.all(res.pressure[:-1] <= 40.0)
    hole = contact_search(c, q0, lambda xy: -np.inf, max_travel=0.3)
    assert not hole.contact
    assert hole.travel == pytest.approx(0.3, abs=0.01)


@settings(deadline=None, max_examples=15)
@given(st.lists(st.floats(-0.5, 0.5), min_size=6, max_size=6))
def test_ptp_property_reaches_goals_near_nominal(dq: list[float]) -> None:
    """Any pose within +-0.5 rad per joint of the nominal pose is reached, in bounded steps."""
    r = get_robot("abb_irb4600_60_205")
    c = Clik(r, "pose")
    q_goal = np.clip(r.q_nominal + np.asarray(dq), r.joint_limits[:, 0], r.joint_limits[:, 1])
    goal = r.fk(q_goal)
    res = c.ptp(r.q_nominal, goal, tol_position=1e-7, tol_rotation=1e-7)
    assert res.converged
    assert np.isfinite(res.q).all() and r.within_limits(res.q).all()
    steps = np.abs(np.diff(res.q, axis=0))
    assert steps.size == 0 or steps.max() <= c.gains.max_joint_step + 1e-12
