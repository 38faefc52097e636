"""Configuration continuity: one configuration per package, no needless swings, each reported."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from program_cases import PROJECT, T_WORLD_BASE, make_pose

from fabflow.design.elements import Element
from fabflow.programs.assemble import compile_program
from fabflow.programs.motion_checks import (
    avoidable_swings,
    configuration_of,
    needless_swings,
    program_checks,
    wrist_flips,
)
from fabflow.programs.motions import work_package_motion
from fabflow.programs.wrist_lin import MAX_DEVIATION_DEG, wrist_interpolated_path
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


def test_a_place_descent_past_the_wrist_singularity_keeps_its_status() -> None:
    """Blocks low in front of the arm: the descent takes the forearm through vertical
    on every branch. The move keeps its status with the wrist axes interpolated: the
    tool centre point stays on the line (checked by forward kinematics), A5 keeps its
    sign, the orientation deviates by at most 2 deg and the target is exact."""
    project = load_project(PROJECT)
    low = [
        Element(f"L{i}", "block", make_pose([2.9 + 0.1 * i, 0.5 + 0.2 * i, 0.3], yaw=0.3 * i))
        for i in range(6)
    ]
    program = compile_program(
        "low", work_package_motion(low, project, T_WORLD_BASE), project, T_WORLD_BASE, {}
    )
    assert program.checks["changes_inside_lin"] == 0
    assert program.checks["wrist_interpolated"] >= 1
    robot = get_robot(project.robot.model)
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
    extra = ("wrist_interpolated", "changes_through_home")
    assert again == {k: v for k, v in program.checks.items() if k not in extra}


def test_an_empty_package_compiles_to_home_and_back() -> None:
    project = load_project(PROJECT)
    program = compile_program("empty", [], project, T_WORLD_BASE, {})
    assert [m.joint for m in program.moves] == [True, True]
    assert program.checks["configuration_changes"] == 0
