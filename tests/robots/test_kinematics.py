"""Machine models: forward kinematics, closed-form and numerical IK, KUKA S/T."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError, UnsupportedError
from fabflow.robots import ROBOT_NAMES, get_robot, kuka_status_turn
from fabflow.robots.catalog import IRB4600_60_205_OPW, KR60_3_OPW
from fabflow.robots.numeric_ik import dls_solve
from fabflow.robots.opw import opw_fk

ARMS_6 = ("kuka_kr60_3", "abb_irb4600_60_205", "ur10e")


def deg(*a: float) -> np.ndarray:
    return np.radians(np.array(a, dtype=float))


def Ry(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def wrap(a: np.ndarray) -> np.ndarray:
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


# ------------------------------------------------------------------ catalogue


def test_get_robot_names_and_fields() -> None:
    assert set(ROBOT_NAMES) == {
        "kuka_kr60_3",
        "ur10e",
        "abb_irb4600_60_205",
        "brokk_170",
        "excavator_gripper",
        "excavator_printer",
    }
    for name in ROBOT_NAMES:
        r = get_robot(name)
        assert r.name == name
        assert r.joint_limits.shape == (r.dof, 2)
        assert np.all(r.joint_limits[:, 0] < r.joint_limits[:, 1])
        assert r.reach > 1.0
    assert get_robot("brokk_170").dof == 5 and get_robot("brokk_170").approximate
    assert not get_robot("kuka_kr60_3").approximate


def test_unknown_robot_lists_known_names() -> None:
    with pytest.raises(UnsupportedError) as exc:
        get_robot("kuka_kr6")
    for name in ROBOT_NAMES:
        assert name in str(exc.value)


def test_bad_joint_shape_is_input_error() -> None:
    with pytest.raises(InputError):
        get_robot("kuka_kr60_3").fk(np.zeros(5))
    with pytest.raises(InputError):
        get_robot("kuka_kr60_3").ik(np.eye(3))


# ------------------------------------------------------------ hand-computed FK


def test_fk_kuka_hand_computed() -> None:
    r = get_robot("kuka_kr60_3")
    # Home: upper arm up, forearm forward (wrist 0.145 above the elbow), flange along +x.
    T = r.fk(deg(0, -90, 90, 0, 0, 0))
    np.testing.assert_allclose(
        T[:3, 3], [0.350 + 0.820 + 0.170, 0, 0.815 + 0.850 + 0.145], atol=1e-12
    )
    np.testing.assert_allclose(T[:3, :3], Ry(np.pi / 2), atol=1e-12)  # KUKA A=0, B=90, C=0
    # All zero: arm stretched forward, forearm offset raises the wrist.
    T = r.fk(np.zeros(6))
    np.testing.assert_allclose(
        T[:3, 3], [0.350 + 0.850 + 0.820 + 0.170, 0, 0.815 + 0.145], atol=1e-12
    )
    # A1 positive turns clockwise seen from above.
    T = r.fk(deg(90, -90, 90, 0, 0, 0))
    np.testing.assert_allclose(T[:3, 3], [0, -1.34, 1.81], atol=1e-12)
    # A5 positive tilts the flange down.
    T = r.fk(deg(0, -90, 90, 0, 90, 0))
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1.17, 0, 1.81 - 0.17], atol=1e-12)


def test_fk_abb_hand_computed() -> None:
    r = get_robot("abb_irb4600_60_205")
    T = r.fk(np.zeros(6))
    np.testing.assert_allclose(
        T[:3, 3], [0.175 + 0.960 + 0.135, 0, 0.495 + 0.900 + 0.175], atol=1e-12
    )
    np.testing.assert_allclose(
        T[:3, :3], Ry(np.pi / 2), atol=1e-12
    )  # tool0 q = (0.707, 0, 0.707, 0)
    T = r.fk(deg(90, 0, 0, 0, 0, 0))  # ABB axis 1 counter-clockwise
    np.testing.assert_allclose(T[:3, 3], [0, 1.27, 1.57], atol=1e-12)
    # Upper arm forward, A3 = -90 deg puts the forearm in line: everything stretched along x.
    T = r.fk(deg(0, 90, -90, 0, 0, 0))
    np.testing.assert_allclose(
        T[:3, 3], [0.175 + 0.900 + 0.960 + 0.135, 0, 0.495 + 0.175], atol=1e-12
    )


def test_fk_ur10e_hand_computed() -> None:
    r = get_robot("ur10e")
    T = r.fk(np.zeros(6))
    d1, a2, a3, d4, d5, d6 = 0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655
    np.testing.assert_allclose(T[:3, 3], [a2 + a3, -(d4 + d6), d1 - d5], atol=1e-12)
    # Zero pose: R = Rx(90 deg) (product of the alphas); the flange faces -y.
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


def test_fk_brokk_hand_computed() -> None:
    r = get_robot("brokk_170")
    T = r.fk(np.zeros(5))
    np.testing.assert_allclose(T[:3, 3], [0.25 + 1.55 + 1.25 + 0.85 + 0.75, 0, 0.70], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [1, 0, 0], atol=1e-12)
    # Boom up 90 deg, everything else straight: all links vertical above the boom foot.
    T = r.fk(deg(0, 90, 0, 0, 0))
    np.testing.assert_allclose(T[:3, 3], [0.25, 0, 0.70 + 1.55 + 1.25 + 0.85 + 0.75], atol=1e-12)
    # Tool pitch is the sum of the pitch joints.
    T = r.fk(deg(30, 20, -60, -30, -20))
    assert np.isclose(np.arctan2(T[2, 2], np.hypot(T[0, 2], T[1, 2])), np.radians(-90))


@pytest.mark.parametrize(
    ("name", "opw"), [("kuka_kr60_3", KR60_3_OPW), ("abb_irb4600_60_205", IRB4600_60_205_OPW)]
)
def test_dh_chain_matches_opw_formulas(name: str, opw: object) -> None:
    r = get_robot(name)
    q = np.random.default_rng(1).uniform(r.joint_limits[:, 0], r.joint_limits[:, 1], (500, 6))
    np.testing.assert_allclose(r.fk(q), opw_fk(opw, q), atol=1e-12)


def test_batch_fk_matches_single() -> None:
    for name in ROBOT_NAMES:
        r = get_robot(name)
        q = np.random.default_rng(2).uniform(r.joint_limits[:, 0], r.joint_limits[:, 1], (7, r.dof))
        Tb = r.fk(q)
        assert Tb.shape == (7, 4, 4)
        for i in range(7):
            np.testing.assert_allclose(Tb[i], r.fk(q[i]), atol=1e-14)
            np.testing.assert_allclose(r.frames_single(q[i]), r.frames(q[i]), atol=1e-14)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_jacobian_matches_finite_differences(name: str) -> None:
    r = get_robot(name)
    q = np.random.default_rng(3).uniform(r.joint_limits[:, 0], r.joint_limits[:, 1], r.dof) * 0.8
    J = r.jacobian(q)
    h = 1e-7
    T0 = r.fk(q)
    for j in range(r.dof):
        dq = np.zeros(r.dof)
        dq[j] = h
        T1 = r.fk(q + dq)
        np.testing.assert_allclose((T1[:3, 3] - T0[:3, 3]) / h, J[:3, j], atol=1e-5)
        W = (T1[:3, :3] - T0[:3, :3]) / h @ T0[:3, :3].T
        np.testing.assert_allclose([W[2, 1], W[0, 2], W[1, 0]], J[3:, j], atol=1e-5)


# ------------------------------------------------------------------ closed form


@pytest.mark.parametrize("name", ARMS_6)
def test_ik_round_trip_10000_poses(name: str) -> None:
    """FK -> IK -> FK to 1e-9 m on 10,000 random reachable poses; the original branch is found."""
    r = get_robot(name)
    rng = np.random.default_rng(10)
    q = rng.uniform(r.joint_limits[:, 0], r.joint_limits[:, 1], (10_000, 6))
    T = r.fk(q)
    qs, valid = r.ik_batch(T, q_ref=q)
    assert valid.any(axis=1).all()
    Ts = r.fk(qs.reshape(-1, 6)).reshape(qs.shape[0], qs.shape[1], 4, 4)
    pos_err = np.linalg.norm(Ts[..., :3, 3] - T[:, None, :3, 3], axis=-1)
    rot_err = np.abs(Ts[..., :3, :3] - T[:, None, :3, :3]).max(axis=(-1, -2))
    assert pos_err[valid].max() < 1e-9
    assert rot_err[valid].max() < 1e-9
    assert r.within_limits(qs[valid]).all()
    # The configuration the pose came from is one of the returned branches.
    dist = np.abs(wrap(qs - q[:, None, :])).max(axis=-1)
    found = np.where(valid, dist, np.inf).min(axis=1) < 1e-6
    assert found.all()


@pytest.mark.parametrize("name", ARMS_6)
def test_ik_finds_every_solution_numerical_search_finds(name: str) -> None:
    """DLS from many seeds never converges to a solution missing from the closed form."""
    r = get_robot(name)
    rng = np.random.default_rng(11)
    n_pose, n_seed = 5, 30
    q = rng.uniform(r.joint_limits[:, 0], r.joint_limits[:, 1], (n_pose, 6))
    T = r.fk(q)
    seeds = rng.uniform(r.joint_limits[:, 0], r.joint_limits[:, 1], (n_pose * n_seed, 6))
    qn, ok = dls_solve(r, np.repeat(T, n_seed, axis=0), seeds, max_iter=100)
    ok &= r.within_limits(qn)
    for k in range(n_pose):
        closed = np.array(r.ik(T[k]))
        found = qn[k * n_seed : (k + 1) * n_seed][ok[k * n_seed : (k + 1) * n_seed]]
        assert len(found) > 0
        for s in found:
            assert np.abs(wrap(closed - s)).max(axis=1).min() < 1e-6


def kuka_pose_near_axis1() -> np.ndarray:
    """A flange pose whose wrist centre is just above axis 1: reachable front and back."""
    T = np.eye(4)
    T[:3, :3] = Ry(2.0) @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    T[:3, 3] = np.array([0.2, 0.1, 1.6]) + KR60_3_OPW.c4 * T[:3, 2]
    return T


def test_kuka_eight_branches_in_open_workspace() -> None:
    r = get_robot("kuka_kr60_3")
    T = kuka_pose_near_axis1()
    q, exists = r.analytic_ik(T[None])
    assert exists.sum() == 8
    Ts = r.fk(q[0])
    np.testing.assert_allclose(Ts, np.broadcast_to(T, Ts.shape), atol=1e-10)
    assert len({tuple(np.round(x, 6)) for x in q[0]}) == 8


def test_ik_sorted_by_reference_and_limits() -> None:
    r = get_robot("kuka_kr60_3")
    q = deg(20, -70, 100, 40, 50, -30)
    sols = r.ik(r.fk(q), q_ref=q)
    np.testing.assert_allclose(sols[0], q, atol=1e-9)
    d = [np.linalg.norm(s - q) for s in sols]
    assert d == sorted(d)
    assert all(r.within_limits(s) for s in sols)
    # Turn variants of A4/A6 (range +-350 deg) appear only when asked for.
    allt = r.ik(r.fk(q), q_ref=q, all_turns=True)
    assert len(allt) > len(sols)
    assert all(r.within_limits(s) for s in allt)


def test_ik_nearest_turn_follows_reference() -> None:
    r = get_robot("ur10e")
    q = deg(10, -80, 70, -100, -90, 300)  # joint 6 beyond half a turn
    sols = r.ik(r.fk(q), q_ref=q)
    np.testing.assert_allclose(sols[0], q, atol=1e-9)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_unreachable_pose_has_no_solution(name: str) -> None:
    r = get_robot(name)
    T = np.eye(4)
    T[:3, 3] = [r.reach + 1.0, 0.0, 1.0]
    assert r.ik(T) == []


@pytest.mark.parametrize(
    ("name", "q_deg"),
    [
        ("kuka_kr60_3", (10, -90, 90, 30, 0, -20)),  # A5 = 0: A4 and A6 aligned
        ("abb_irb4600_60_205", (15, 10, -5, 30, 0, 40)),
        ("ur10e", (20, -70, 60, -30, 0, 40)),  # joint 5 = 0: joints 4 and 6 aligned
    ],
)
def test_wrist_singularity_round_trips_and_keeps_reference(name: str, q_deg: tuple) -> None:
    r = get_robot(name)
    q = deg(*q_deg)
    sols = r.ik(r.fk(q), q_ref=q)
    assert sols
    for s in sols:
        np.testing.assert_allclose(r.fk(s), r.fk(q), atol=1e-12)
    # Only the sum of the aligned joints is determined; the reference settles the split.
    np.testing.assert_allclose(sols[0], q, atol=1e-9)
    # Close to (not at) the singularity the closed form stays exact.
    q_near = q.copy()
    q_near[4] = 1e-9
    for s in r.ik(r.fk(q_near), q_ref=q_near):
        np.testing.assert_allclose(r.fk(s), r.fk(q_near), atol=1e-9)


@settings(deadline=None, max_examples=40)
@given(
    st.sampled_from(ARMS_6),
    st.lists(st.floats(0.02, 0.98), min_size=6, max_size=6),
)
def test_ik_round_trip_property(name: str, u: list[float]) -> None:
    r = get_robot(name)
    lo, hi = r.joint_limits[:, 0], r.joint_limits[:, 1]
    q = lo + np.asarray(u) * (hi - lo)
    T = r.fk(q)
    sols = r.ik(T, q_ref=q)
    assert sols
    for s in sols:
        assert np.linalg.norm(r.fk(s)[:3, 3] - T[:3, 3]) < 1e-9


# ------------------------------------------------------------------ numerical


def test_dls_batch_converges_from_nearby_seeds() -> None:
    r = get_robot("abb_irb4600_60_205")
    rng = np.random.default_rng(12)
    q = rng.uniform(r.joint_limits[:, 0] * 0.7, r.joint_limits[:, 1] * 0.7, (200, 6))
    T = r.fk(q)
    qn, ok = dls_solve(r, T, q + rng.normal(0, 0.2, q.shape))
    assert ok.mean() > 0.95
    np.testing.assert_allclose(r.fk(qn[ok])[:, :3, 3], T[ok, :3, 3], atol=1e-9)


def test_brokk_ik_round_trip_and_family() -> None:
    r = get_robot("brokk_170")
    rng = np.random.default_rng(13)
    for _ in range(3):
        q = rng.uniform(r.joint_limits[:, 0] * 0.8, r.joint_limits[:, 1] * 0.8)
        T = r.fk(q)
        sols = r.ik(T, q_ref=q)
        assert sols
        np.testing.assert_allclose(sols[0], q, atol=1e-6)
        for s in sols:
            assert np.linalg.norm(r.fk(s)[:3, 3] - T[:3, 3]) < 1e-9
            assert r.within_limits(s)
        # Redundant machine: several members of the solution family, all exact.
        family = r.ik(T)
        assert len(family) >= 2
        np.testing.assert_allclose(
            r.fk(np.array(family)), np.broadcast_to(T, (len(family), 4, 4)), atol=1e-9
        )


# ------------------------------------------------------------------ KUKA S / T


def test_kuka_status_turn_known_values() -> None:
    assert kuka_status_turn(deg(0, -90, 90, 0, 10, 0)) == (2, 2)
    assert kuka_status_turn(deg(0, -90, 90, 0, -10, 0)) == (6, 2 | 16)
    # Forearm folded back over the shoulder: wrist behind axis 1 (overhead), A3 below phi.
    assert kuka_status_turn(deg(0, -90, -80, 0, 10, 0)) == (1, 2 | 4)
    # Turn bits: every negative axis.
    assert kuka_status_turn(deg(-10, -90, 90, -5, 10, -1))[1] == 1 | 2 | 8 | 32


def test_kuka_status_turn_batch_and_branches() -> None:
    r = get_robot("kuka_kr60_3")
    q, exists = r.analytic_ik(kuka_pose_near_axis1()[None])
    S, Tn = kuka_status_turn(q[0][exists[0]])
    assert S.shape == (8,)
    # The 8 branches are exactly the 8 status values: S identifies the branch.
    assert sorted(S.tolist()) == list(range(8))
    assert Tn.dtype.kind == "i"


@pytest.mark.parametrize("name", ["kuka_kr60_3", "abb_irb4600_60_205"])
@pytest.mark.parametrize("arms", [[0], [0, 3], [1, 2], [3, 1, 3], []])
@pytest.mark.parametrize("per_pose", [False, True])
def test_ik_batch_of_some_arm_branches_is_those_of_all(
    name: str, arms: list[int], per_pose: bool
) -> None:
    robot = get_robot(name)
    rng = np.random.default_rng(7)
    T = robot.fk(rng.uniform(-2.0, 2.0, (300, 6)))
    q_ref = rng.uniform(-4.0, 4.0, (300, 6)) if per_pose else np.full(6, 0.3)
    q, valid = robot.ik_batch(T, q_ref=q_ref)
    q_some, valid_some = robot.ik_batch(T, q_ref=q_ref, arms=arms)
    solved = np.zeros(8, dtype=bool)
    solved[np.r_[arms, np.asarray(arms, dtype=int) + 4].astype(int)] = True
    assert np.array_equal(q_some[:, solved], q[:, solved], equal_nan=True)
    assert np.array_equal(valid_some[:, solved], valid[:, solved])
    assert np.isnan(q_some[:, ~solved]).all() and not valid_some[:, ~solved].any()


def test_ik_batch_solves_every_branch_of_an_arm_without_an_opw_geometry() -> None:
    robot = get_robot("ur10e")
    T = robot.fk(np.random.default_rng(8).uniform(-2.0, 2.0, (50, 6)))
    q, valid = robot.ik_batch(T)
    q_some, valid_some = robot.ik_batch(T, arms=[0])
    assert np.array_equal(q_some, q, equal_nan=True) and np.array_equal(valid_some, valid)
