"""Configuration continuity: one configuration per package, no needless swings, each reported."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from program_cases import PROJECT, T_WORLD_BASE, make_pose

from fabflow.design.elements import Element
from fabflow.programs.assemble import _configurations, compile_program
from fabflow.programs.feasibility import solve_moves
from fabflow.programs.ir import Program
from fabflow.programs.motion_checks import (
    avoidable_swings,
    configuration_of,
    needless_swings,
    program_checks,
    wrist_flips,
)
from fabflow.programs.motions import Waypoint, work_package_motion
from fabflow.programs.wrist_lin import MAX_DEVIATION_DEG, joint_move_bow, wrist_interpolated_path
from fabflow.project import load_project
from fabflow.robots import get_robot
from fabflow.transforms.so3 import exp_so3, log_so3

ROBOTS = ["kuka_kr60_3", "abb_irb4600_60_205", "ur10e"]


@pytest.mark.parametrize("name", ROBOTS)
@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6))
def test_configuration_is_the_branch_the_joint_values_lie_on(name: str, u: list[float]) -> None:
    robot = get_robot(name)
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    q = (lo + hi) / 2 + np.asarray(u) * (hi - lo) / 2 * 0.95
    q[4] = np.copysign(max(abs(q[4]), 0.05), q[4])  # away from the wrist singularity
    branch = int(configuration_of(robot, q[None])[0])
    assert branch >= 0
    q_all, _ = robot.ik_batch(robot.fk(q[None]), q_ref=q)
    diff = (q_all[0, branch] - q + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(diff).max() < 1e-4


def test_needless_swings_flags_an_elbow_flip_and_a_turn_around() -> None:
    robot = get_robot("kuka_kr60_3")
    q0 = np.radians([10.0, -60.0, 80.0, 0.0, 40.0, 0.0])
    small = q0 + np.radians([5.0, 10.0, -10.0, 20.0, 10.0, 30.0])
    elbow = q0 + np.radians([0.0, 30.0, 100.0, 0.0, 0.0, 0.0])
    around = q0 + np.radians([120.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # azimuth moves as much
    long_way = q0.copy()
    q0_back, long_way[0] = q0.copy(), np.radians(-170.0)
    q0_back[0] = np.radians(170.0)  # 20 deg apart, but A1 turns 340 deg
    flags = needless_swings(
        robot, np.stack([q0, q0, q0, q0_back]), np.stack([small, elbow, around, long_way])
    )
    assert flags.tolist() == [False, True, False, True]


def test_a_swing_into_another_elbow_is_avoidable() -> None:
    robot = get_robot("kuka_kr60_3")
    q0 = np.radians([10.0, -60.0, 80.0, 0.0, 40.0, 0.0])
    q_all, ok = robot.ik_batch(robot.fk(q0[None]), q_ref=q0)
    elbow = q_all[0, np.flatnonzero(ok[0] & (np.abs(q_all[0, :, 2] - q0[2]) > np.pi / 2))[0]]
    assert needless_swings(robot, q0[None], elbow[None])[0]
    # the same pose as the start: its own configuration is no swing at all
    assert avoidable_swings(robot, q0[None], robot.fk(elbow[None]))[0]
    # a target out of the reach is no option at all
    out = robot.fk(q0[None])
    out[0, :3, 3] *= 10.0
    assert not avoidable_swings(robot, q0[None], out)[0]


def test_wrist_flips_is_a_sign_change_of_a5() -> None:
    path = np.zeros((3, 6))
    path[:, 4] = [0.2, 0.05, 0.1]
    assert not wrist_flips(path)
    path[2, 4] = -0.01
    assert wrist_flips(path)


def _blocks(n: int) -> list[Element]:
    """A row of blocks in front of the test station."""
    return [
        Element(f"B{i}", "block", make_pose([3.2 + 0.1 * i, 0.5 + 0.2 * i, 0.6], yaw=0.3 * i))
        for i in range(n)
    ]


def _low_blocks_program(seated: bool) -> Program:
    """Blocks low in front of the arm: the descent takes the forearm through vertical on
    every branch. ``seated=False`` compiles their descents as if they held nothing."""
    project = load_project(PROJECT)
    low = [
        Element(f"L{i}", "block", make_pose([2.9 + 0.1 * i, 0.5 + 0.2 * i, 0.3], yaw=0.3 * i))
        for i in range(6)
    ]
    steps = work_package_motion(low, project, T_WORLD_BASE)
    if not seated:
        steps = [
            dataclasses.replace(s, seated=False) if isinstance(s, Waypoint) else s for s in steps
        ]
    return compile_program("low", steps, project, T_WORLD_BASE, {})


def test_an_unheld_descent_past_the_wrist_singularity_keeps_its_status() -> None:
    """The move keeps its status with the wrist axes interpolated: the tool centre point
    stays on the line (checked by forward kinematics), A5 keeps its sign, the
    orientation deviates by at most 2 deg and the target is exact."""
    program = _low_blocks_program(seated=False)
    assert program.checks["changes_inside_lin"] == 0
    assert program.checks["wrist_interpolated"] >= 1
    robot = get_robot("kuka_kr60_3")
    moves = program.moves
    for k, m in enumerate(moves):
        if not m.wrist_interpolated:
            continue
        path = np.vstack([moves[k - 1].q, m.via_q, m.q])
        assert not wrist_flips(path)
        T = program.T_base_world @ np.stack([moves[k - 1].T_world_tool, m.T_world_tool])
        T_tool = robot.fk(path) @ program.T_flange_tool
        p0, p1 = T[0, :3, 3], T[1, :3, 3]
        u = (p1 - p0) / np.linalg.norm(p1 - p0)
        off_line = (T_tool[:, :3, 3] - p0) - np.outer((T_tool[:, :3, 3] - p0) @ u, u)
        assert np.abs(off_line).max() < 1e-5
        assert np.allclose(T_tool[-1], T[1], atol=1e-6)
        # the orientation against the straight move's (the geodesic between the ends)
        s = np.arange(len(path)) / (len(path) - 1)
        w = log_so3((T[0, :3, :3].T @ T[1, :3, :3])[None])[0]
        R_line = T[0, :3, :3] @ exp_so3(s[:, None] * w)
        off = np.linalg.norm(log_so3(R_line.transpose(0, 2, 1) @ T_tool[:, :3, :3]), axis=1)
        assert np.degrees(off).max() <= MAX_DEVIATION_DEG + 1e-6
        # the poses the program carries are the ones the joints take
        via = program.T_base_world @ m.via_T_world_tool
        assert np.allclose(via, T_tool[1:-1], atol=1e-9)


def test_a_held_block_goes_past_the_wrist_singularity_by_a_joint_move() -> None:
    """A block held into its seat must not turn on the way (2 deg swings the ends of a
    0.6 m block by 10 mm): where its descent passes the singularity it becomes a joint
    move through A5 = 0 with A1, A4 and A6 standing still. Checked by forward
    kinematics of the joint interpolation: the tool stays within 5 mm of the line, the
    orientation stays the ends' and the target is exact; the program goes back to its
    configuration on the way up, so the wrist passes 0 twice and nothing else changes."""
    program = _low_blocks_program(seated=True)
    checks = program.checks
    assert checks["changes_inside_lin"] == 0 and checks["wrist_interpolated"] == 0
    assert checks["joint_through_wrist"] >= 2
    assert checks["configuration_changes"] == checks["joint_through_wrist"]
    assert "joint moves through the wrist singularity" in program.header
    robot = get_robot("kuka_kr60_3")
    moves = program.moves
    placing = ("place", "place retract")
    passes = [k for k, m in enumerate(moves) if m.kind == "ptp" and m.label in placing]
    assert len(passes) == checks["joint_through_wrist"]
    assert "place" in {moves[k].label for k in passes}
    for k in passes:
        q0, q1 = moves[k - 1].q, moves[k].q
        assert np.sign(q0[4]) != np.sign(q1[4])  # A5 through 0
        np.testing.assert_allclose(q1[[0, 3, 5]], q0[[0, 3, 5]], atol=1e-9)
        s = np.linspace(0.0, 1.0, 101)[:, None]
        T_tool = robot.fk(q0 + s * (q1 - q0)) @ program.T_flange_tool
        T = program.T_base_world @ np.stack([moves[k - 1].T_world_tool, moves[k].T_world_tool])
        p0, p1 = T[0, :3, 3], T[1, :3, 3]
        u = (p1 - p0) / np.linalg.norm(p1 - p0)
        off_line = (T_tool[:, :3, 3] - p0) - np.outer((T_tool[:, :3, 3] - p0) @ u, u)
        assert np.linalg.norm(off_line, axis=1).max() <= 0.005
        turn = np.linalg.norm(log_so3(T[0, :3, :3].T @ T_tool[:, :3, :3]), axis=1)
        assert np.degrees(turn).max() < 1e-6
        assert np.allclose(T_tool[-1], T[1], atol=1e-6)
        if moves[k].label == "place":  # the line's time at the line's speed (no dwell before)
            line_time = np.linalg.norm(p1 - p0) / load_project(PROJECT).program.speed
            assert moves[k].time - moves[k - 1].time == pytest.approx(line_time, rel=1e-3)


def test_a_joint_move_bows_off_the_line_and_turns_as_forward_kinematics_says() -> None:
    robot = get_robot("kuka_kr60_3")
    T_flange_tool = np.eye(4)
    T_flange_tool[2, 3] = 0.25
    q0 = np.radians([134.2, -41.4, 128.7, 0.0, 2.7, -135.5])
    assert joint_move_bow(robot, q0, q0, T_flange_tool) == (0.0, 0.0)
    # A2, A3 and A5 turn about parallel axes: equal sums keep the tool's orientation
    q1 = q0 + np.radians([0.0, 9.7, -3.7, 0.0, -6.0, 0.0])
    bow, turn = joint_move_bow(robot, q0, q1, T_flange_tool)
    assert 0.001 < bow < 0.005 and turn < 1e-9
    # A1 alone: the tool runs on a circle about the base axis, whose sagitta is the bow,
    # and turns about that axis, as the geodesic between the ends does
    q2 = q0 + np.radians([30.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    rho = np.hypot(*(robot.fk(q0[None]) @ T_flange_tool)[0, :2, 3])
    bow, turn = joint_move_bow(robot, q0, q2, T_flange_tool)
    assert bow == pytest.approx(rho * (1.0 - np.cos(np.radians(15.0))), rel=1e-3)
    assert turn < 1e-9
    # A4 and A6 turning against each other with A5 off 0 tilt the tool off the geodesic
    q3 = np.radians([20.0, -60.0, 100.0, 0.0, 20.0, 0.0])
    _, turn = joint_move_bow(robot, q3, q3 + np.radians([0, 0, 0, 90, 0, -90]), T_flange_tool)
    assert np.degrees(turn) > 5.0


def test_a_free_move_past_the_wrist_singularity_keeps_its_configuration() -> None:
    """The empty tool drawn in to a tuck radius at the height where the forearm passes
    vertical: the line takes A5 through 0. As a ``free`` move it becomes a joint move
    to the end of the same configuration (A4 and A6 half a turn on), as a plain one
    it stays a linear move through A5 = 0 (counted as such)."""
    robot = get_robot("kuka_kr60_3")
    T_flange_tool = np.eye(4)
    T_flange_tool[2, 3] = 0.25
    q_out = np.radians([142.4, -27.9, 78.5, 0.0, 39.3, 52.2])
    q_in = np.radians([142.4, -53.8, 150.5, 0.0, -6.7, 52.2])
    T_out, T_in = robot.fk(np.stack([q_out, q_in])) @ T_flange_tool
    eye = np.eye(4)
    for free in (True, False):
        waypoints = [
            Waypoint("ptp", T_out, 0.5, 0.0, "depart", "E"),
            Waypoint("lin", T_in, 0.25, 0.0, "tuck in", "E", free=free),
        ]
        q, via_q, _, _, wrist, joint = solve_moves(
            waypoints, robot.name, eye, T_flange_tool, q_start=q_out
        )
        assert np.allclose(robot.fk(q[1][None]) @ T_flange_tool, T_in, atol=1e-9)
        if free:
            assert joint[1] and not wrist[1] and via_q[1] is None
            assert configuration_of(robot, q)[0] == configuration_of(robot, q)[1]
            assert q[1][4] > 0.0 and abs(abs(q[1][3] - q[0][3]) - np.pi) < 1e-6
        else:
            assert not joint[1] and wrist_flips(np.vstack([q[0], via_q[1], q[1]]))


def test_wrist_interpolation_of_a_standing_move_is_exact() -> None:
    robot = get_robot("kuka_kr60_3")
    q = np.radians([10.0, -60.0, 80.0, 30.0, 20.0, -40.0])
    T_flange_tool = np.eye(4)
    T_flange_tool[2, 3] = 0.25
    T = np.repeat((robot.fk(q) @ T_flange_tool)[None], 3, axis=0)
    path, deviation = wrist_interpolated_path(robot, q, q, T, T_flange_tool)
    assert np.allclose(path, q) and deviation < 1e-9


def test_a_package_keeps_one_configuration_and_repeats_its_pick_exactly() -> None:
    project = load_project(PROJECT)
    steps = work_package_motion(_blocks(6), project, T_WORLD_BASE)
    program = compile_program("row", steps, project, T_WORLD_BASE, {})
    assert program.moves[0].joint and program.moves[-1].joint  # HOME to HOME
    moves = program.moves
    robot = get_robot(project.robot.model)
    q = np.stack([m.q for m in moves])
    assert len(set(configuration_of(robot, q[1:-1]).tolist())) == 1
    # the same joint values each time, but for A1: the magazine stands right
    # behind the arm, where A1 may take either end of its range (+-180 deg)
    picks = np.stack([m.q for m in moves if m.label == "pick approach"])
    assert np.abs(picks[:, 1:] - picks[0, 1:]).max() < 1e-9
    assert np.allclose(np.abs(picks[:, 0]), np.pi)
    assert program.checks["configuration_changes"] == 0
    assert program.checks["changes_inside_lin"] == 0
    T_flange = program.T_base_world @ np.stack([m.T_world_tool for m in moves])
    T_flange = T_flange @ np.linalg.inv(program.T_flange_tool)
    joint = np.array([m.joint for m in moves])
    again = program_checks(
        robot, [m.kind for m in moves], q, [m.via_q for m in moves], T_flange, joint=joint
    )
    extra = ("wrist_interpolated", "joint_through_wrist", "changes_through_home")
    assert again == {k: v for k, v in program.checks.items() if k not in extra}


def test_an_empty_package_compiles_to_home_and_back() -> None:
    project = load_project(PROJECT)
    program = compile_program("empty", [], project, T_WORLD_BASE, {})
    assert [m.joint for m in program.moves] == [True, True]
    assert program.checks["configuration_changes"] == 0


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 30))
def test_the_executed_moves_take_their_targets_configurations(seed: int, n: int) -> None:
    # a program's checks read the configurations its compile solved for the targets:
    # a move whose joint values are its target's to the bit takes the target's, the
    # HOME moves and the targets whose A1 was turned a whole turn are solved again
    rng = np.random.default_rng(seed)
    robot = get_robot("kuka_kr60_3")
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    q_solved = lo + rng.uniform(0.05, 0.95, (n, 6)) * (hi - lo)
    config = configuration_of(robot, q_solved)
    q_home = (lo + hi) / 2
    origin = [-1]
    rows = [q_home]
    for k in range(n):
        if rng.random() < 0.2:
            origin.append(-1)
            rows.append(q_home)
        q = q_solved[k].copy()
        if rng.random() < 0.3:
            q[0] += 2 * np.pi * rng.choice([-1.0, 1.0])  # the turn settle_a1_turns makes
        origin.append(k)
        rows.append(q)
    origin.append(-1)
    rows.append(q_home)
    q_executed = np.stack(rows)
    got = _configurations(robot, q_executed, np.array(origin), q_solved, config)
    np.testing.assert_array_equal(got, configuration_of(robot, q_executed))
