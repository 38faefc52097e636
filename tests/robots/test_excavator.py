"""The excavator arm with the rotating gripper: FK, closed-form IK, catalogue entries."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.robots import get_robot, reach_map
from fabflow.robots.catalog import (
    HEAP_GRIPPER,
    controller_profile,
    format_mismatch,
    formats_of,
    robot_setup_problems,
    vendor_of,
)
from fabflow.robots.geometry import link_segments, shoulder_radius
from fabflow.transforms.so3 import R_FLIP_X, log_so3

NAME = "excavator_gripper"
P = HEAP_GRIPPER


def deg(*a: float) -> np.ndarray:
    return np.radians(np.array(a, dtype=float))


def wrap(a: np.ndarray) -> np.ndarray:
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


def Rz(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_error(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of the rotation between two orientations (radians)."""
    return float(np.linalg.norm(log_so3((R_a @ R_b.T)[None])[0]))


def home_wrist_centre() -> np.ndarray:
    """Wrist centre at home (boom 30 deg, stick -100 deg): stick 70 deg below horizontal."""
    x = P.a1 + P.a2 * np.cos(np.radians(30)) + P.a3 * np.cos(np.radians(-70))
    z = P.d1 + P.a2 * np.sin(np.radians(30)) + P.a3 * np.sin(np.radians(-70))
    return np.array([x, 0.0, z])


# ------------------------------------------------------------------ catalogue


def test_catalogue_entry() -> None:
    r = get_robot(NAME)
    assert r.dof == 6 and r.approximate and r.payload == 4000.0
    assert r.analytic_ik is not None
    assert np.isclose(r.reach, 7.4)
    np.testing.assert_allclose(
        np.degrees(r.joint_limits),
        [[-180, 180], [-40, 70], [-150, -30], [-90, 90], [-45, 45], [-360, 360]],
    )
    assert r.within_limits(r.q_home) and r.within_limits(r.q_nominal)
    assert np.all((np.degrees(r.velocity_limits) >= 20) & (np.degrees(r.velocity_limits) <= 40))
    # Home and nominal: gripper pointing straight down in front of the machine.
    for q in (r.q_home, r.q_nominal):
        T = r.fk(q)
        np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)
        assert T[0, 3] > 4.0 and abs(T[1, 3]) < 1e-12


def test_vendor_controller_and_formats() -> None:
    assert vendor_of(NAME) == "heap"
    assert formats_of(NAME) == ("json",)
    assert controller_profile(NAME).module_motions is None
    assert controller_profile(NAME) is controller_profile(NAME, "heap_gateway")
    why = format_mismatch("krl", NAME)
    assert why is not None and "'json'" in why and "Menzi Muck" in why
    assert robot_setup_problems(NAME, None, 2800.0) == []
    assert robot_setup_problems(NAME, None, 4500.0)


def test_link_capsules() -> None:
    r = get_robot(NAME)
    seg, radii, names = link_segments(r, r.q_home[None])
    assert names == ["boom foot", "boom", "stick", "tiltrotator"]
    np.testing.assert_allclose(radii, [0.40, 0.25, 0.25, 0.30])
    np.testing.assert_allclose(seg[0, 2, 1], home_wrist_centre(), atol=1e-12)
    np.testing.assert_allclose(seg[0, 3, 1], r.fk(r.q_home)[:3, 3], atol=1e-12)
    assert np.isclose(shoulder_radius(r), P.a1 + 0.40)


# ------------------------------------------------------------ hand-computed FK


def test_fk_all_zero_stretched_forward() -> None:
    T = get_robot(NAME).fk(np.zeros(6))
    np.testing.assert_allclose(T[:3, 3], [P.a1 + P.a2 + P.a3 + P.d6, 0, P.d1], atol=1e-12)
    # Gripper continuing the stick: approach forward, x up, y (jaws) to the right.
    np.testing.assert_allclose(T[:3, :3], [[0, 0, 1], [0, -1, 0], [1, 0, 0]], atol=1e-12)


def test_fk_home_gripper_down() -> None:
    r = get_robot(NAME)
    T = r.fk(deg(0, 30, -100, -20, 0, 0))
    np.testing.assert_allclose(T[:3, 3], home_wrist_centre() - [0, 0, P.d6], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [4.819152, 0, 1.050768], atol=1e-6)
    np.testing.assert_allclose(T[:3, :3], R_FLIP_X, atol=1e-12)


def test_fk_boom_up_stick_level() -> None:
    # Boom vertical, stick level forward, gripper continuing the stick.
    T = get_robot(NAME).fk(deg(0, 90, -90, 0, 0, 0))
    np.testing.assert_allclose(T[:3, 3], [P.a1 + P.a3 + P.d6, 0, P.d1 + P.a2], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [1, 0, 0], atol=1e-12)
    # Wrist pitch -90 deg turns the gripper down about the wrist centre.
    T = get_robot(NAME).fk(deg(0, 90, -90, -90, 0, 0))
    np.testing.assert_allclose(T[:3, 3], [P.a1 + P.a3, 0, P.d1 + P.a2 - P.d6], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], R_FLIP_X, atol=1e-12)


def test_fk_slew_tilt_and_rotator() -> None:
    r = get_robot(NAME)
    home = deg(0, 30, -100, -20, 0, 0)
    w = home_wrist_centre()
    # Slew +90 deg: counter-clockwise seen from above, the arm points along +y.
    T = r.fk(home + deg(90, 0, 0, 0, 0, 0))
    np.testing.assert_allclose(T[:3, 3], [0, w[0], w[2] - P.d6], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], Rz(np.pi / 2) @ R_FLIP_X, atol=1e-12)
    # Tilt +30 deg about the forward axis through the wrist centre: gripper swings left.
    T = r.fk(home + deg(0, 0, 0, 0, 30, 0))
    z = np.array([0.0, np.sin(np.radians(30)), -np.cos(np.radians(30))])
    np.testing.assert_allclose(T[:3, 2], z, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], w + P.d6 * z, atol=1e-12)
    np.testing.assert_allclose(T[:3, 0], [1, 0, 0], atol=1e-12)
    # Rotator +90 deg turns the jaws about the approach axis (right-handed about z).
    T = r.fk(home + deg(0, 0, 0, 0, 0, 90))
    np.testing.assert_allclose(T[:3, :3], R_FLIP_X @ Rz(np.pi / 2), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], w - [0, 0, P.d6], atol=1e-12)


# ------------------------------------------------------------------ Jacobian


@pytest.mark.parametrize("q_deg", [(0, 30, -100, -20, 0, 0), (40, -20, -60, 50, 35, -250)])
def test_jacobian_matches_finite_differences(q_deg: tuple[float, ...]) -> None:
    r = get_robot(NAME)
    q = deg(*q_deg)
    J = r.jacobian(q)
    h = 1e-6
    T0 = r.fk(q)
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = h
        Tp, Tm = r.fk(q + dq), r.fk(q - dq)
        np.testing.assert_allclose((Tp[:3, 3] - Tm[:3, 3]) / (2 * h), J[:3, j], atol=1e-7)
        W = (Tp[:3, :3] - Tm[:3, :3]) / (2 * h) @ T0[:3, :3].T
        np.testing.assert_allclose([W[2, 1], W[0, 2], W[1, 0]], J[3:, j], atol=1e-7)


# ------------------------------------------------------------------ closed form


@settings(deadline=None, max_examples=50)
@given(st.lists(st.floats(0.0, 1.0), min_size=6, max_size=6))
def test_ik_gives_back_the_configuration_the_pose_came_from(u: list[float]) -> None:
    """Beyond the position round trip of every robot: the orientation, and q itself first."""
    r = get_robot(NAME)
    q = r.joint_limits[:, 0] + np.asarray(u) * np.ptp(r.joint_limits, axis=1)
    T = r.fk(q)
    sols = np.array(r.ik(T, q_ref=q))
    assert len(sols) and r.within_limits(sols).all()
    rotations = r.fk(sols)[:, :3, :3]
    assert max(rotation_error(R, T[:3, :3]) for R in rotations) < 1e-9
    assert np.abs(wrap(sols - q)).max(axis=1).min() < 1e-9
    np.testing.assert_allclose(sols[0], q, atol=1e-9)


def test_eight_branches_one_within_limits() -> None:
    r = get_robot(NAME)
    T = r.fk(r.q_home)
    q, exists = r.analytic_ik(T[None])
    assert q.shape == (1, 8, 6) and exists.shape == (1, 8)
    # Near the machine every branch exists; each reproduces the pose and all differ.
    assert exists.all()
    Ts = r.fk(q[0])
    np.testing.assert_allclose(Ts, np.broadcast_to(T, Ts.shape), atol=1e-12)
    assert len({tuple(np.round(x, 6)) for x in q[0]}) == 8
    # Behind branches slew half a turn; the second wrist branch tilts beyond 90 deg.
    np.testing.assert_allclose(wrap(q[0, 4:, 0] - q[0, :4, 0]), np.pi, atol=1e-12)
    assert np.all(np.abs(q[0, 0::2, 4]) <= np.pi / 2)
    assert np.all(np.abs(q[0, 1::2, 4]) > np.pi / 2)
    # The stick folds down on the even elbow branches, up on the others.
    assert np.all(q[0, [0, 1, 4, 5], 2] <= 0) and np.all(q[0, [2, 3, 6, 7], 2] >= 0)
    # Within the excavator's limits only the first branch remains.
    _, valid = r.ik_batch(T[None])
    np.testing.assert_array_equal(valid[0], [True] + [False] * 7)
    sols = r.ik(T)
    assert len(sols) == 1
    np.testing.assert_allclose(sols[0], r.q_home, atol=1e-12)


def test_rotator_beyond_half_a_turn_follows_reference() -> None:
    r = get_robot(NAME)
    q = deg(10, 20, -80, -30, 15, 300)
    sols = r.ik(r.fk(q), q_ref=q)
    assert len(sols) == 1
    np.testing.assert_allclose(sols[0], q, atol=1e-9)
    # Without a reference the rotator takes the turn nearest 0; all_turns lists both.
    np.testing.assert_allclose(r.ik(r.fk(q))[0][5], np.radians(-60), atol=1e-9)
    allt = r.ik(r.fk(q), all_turns=True)
    np.testing.assert_allclose(sorted(np.degrees([s[5] for s in allt])), [-60, 300], atol=1e-6)


def test_unreachable_pose_has_no_solution() -> None:
    r = get_robot(NAME)
    # Wrist centre beyond boom + stick from the boom pivot.
    T = np.eye(4)
    T[:3, :3] = R_FLIP_X
    T[:3, 3] = [P.a1 + P.a2 + P.a3 + 0.1, 0.0, P.d1 + P.d6]
    _, exists = r.analytic_ik(T[None])
    assert not exists[0, :4].any()
    assert r.ik(T) == []
    # Within the arm's reach, but pointing up is beyond the wrist pitch limit.
    T = r.fk(r.q_home)
    T[:3, :3] = np.diag([1.0, 1.0, 1.0])
    _, exists = r.analytic_ik(T[None])
    assert exists[0, 0]
    assert r.ik(T) == []


def test_ik_batch_matches_single_calls() -> None:
    r = get_robot(NAME)
    rng = np.random.default_rng(7)
    q = rng.uniform(r.joint_limits[:, 0], r.joint_limits[:, 1], (200, 6))
    T = r.fk(q)
    qs, valid = r.ik_batch(T, q_ref=q)
    assert qs.shape == (200, 8, 6) and valid.shape == (200, 8)
    assert (valid.sum(axis=1) == 1).all()
    Ts = r.fk(qs[valid])
    np.testing.assert_allclose(Ts, T, atol=1e-9)
    np.testing.assert_allclose(qs[valid], q, atol=1e-9)
    for k in (0, 99, 199):
        np.testing.assert_allclose(r.ik(T[k], q_ref=q[k])[0], qs[k][valid[k]][0], atol=1e-12)


def test_reach_map_holds_the_home_pose() -> None:
    r = get_robot(NAME)
    tool = np.eye(4)
    tool[2, 3] = 0.6
    rm = reach_map(NAME, tool, step=0.2, disk_cache=False)
    assert rm.n_yaw == 12
    p = (r.fk(r.q_nominal) @ tool)[:3, 3]
    assert rm.reachable(p)[0]
    assert rm.r_max <= r.reach + 0.6 + 0.2 + 1e-9
    assert not rm.reachable([r.reach + 1.0, 0.0, 1.0])[0]
