"""Programs are checked by inverse kinematics along every move before anything is written."""

from __future__ import annotations

import numpy as np
import pytest
from program_cases import PROJECT, T_WORLD_BASE, make_pose

from fabflow.design.elements import Element
from fabflow.errors import InfeasibleError
from fabflow.programs.assemble import compile_program
from fabflow.programs.ir import Move, Program
from fabflow.programs.motions import work_package_motion
from fabflow.project import load_project
from fabflow.robots import get_robot


def test_unreachable_target_names_element() -> None:
    project = load_project(PROJECT)
    far = Element(
        "FAR", "task_point", make_pose([9.0, 1.0, 0.3], flip=True), attributes={"action": "mark"}
    )
    steps = work_package_motion([far], project, T_WORLD_BASE)
    with pytest.raises(InfeasibleError, match=r"element FAR, target 'approach'"):
        compile_program("far", steps, project, T_WORLD_BASE, {})


def test_linear_move_through_limit_is_refused() -> None:
    """A linear move straight through the base axis must fail inside the line."""
    project = load_project(PROJECT)
    steps = work_package_motion(
        [
            Element(
                "X",
                "print_path",
                make_pose([2.0, 1.0, 0.0]),
                polyline=np.array([[0.9, -0.9, 0.0], [-0.9, 0.9, 0.0]]),
            )
        ],
        project,
        make_pose([2.0, 1.0, 0.2]),
    )
    with pytest.raises(InfeasibleError, match=r"element X"):
        compile_program("through", steps, project, make_pose([2.0, 1.0, 0.2]), {})


def test_program_moves_carry_valid_configurations(kuka_program: Program) -> None:
    robot = get_robot("kuka_kr60_3")
    q = np.stack([m.q for m in kuka_program.moves])
    assert robot.within_limits(q).all()
    times = [m.time for m in kuka_program.moves]
    assert times == sorted(times) and times[-1] > 0
    assert all(isinstance(m, Move) for m in kuka_program.moves)


@pytest.mark.parametrize("start_a1", [-150.0, -90.0, -30.0])
def test_the_last_target_takes_the_turn_of_a1_nearer_home(start_a1: float) -> None:
    # a target straight behind the arm is A1 = +180 or -180, both within the KR 60's
    # +-185 deg; HOME (A1 = +180) comes after it: the program ends without turning
    # A1 a whole turn at HOME, wherever the arm comes from
    from fabflow.programs.feasibility import solve_moves
    from fabflow.programs.motions import Waypoint

    robot = get_robot("kuka_kr60_3")
    q_home = np.radians([180.0, -110.0, 150.0, 0.0, 50.0, 0.0])
    q_behind = np.radians([180.0, -100.0, 130.0, 0.0, 60.0, 0.0])
    T_tool = robot.fk(q_behind)  # flange as tool, base as world
    start = np.radians([start_a1, -100.0, 130.0, 0.0, 60.0, 0.0])
    target = [Waypoint("ptp", T_tool, 0.5, 0.0, "behind", "E")]
    eye = np.eye(4)
    alone, *_ = solve_moves(target, robot.name, eye, eye, q_start=start)
    homed, *_ = solve_moves(target, robot.name, eye, eye, q_start=start, q_end=q_home)
    assert np.degrees(alone[0, 0]) == pytest.approx(-180.0)  # the nearer turn from the start
    assert np.degrees(homed[0, 0]) == pytest.approx(180.0)  # the turn HOME is at
    np.testing.assert_allclose(homed[0, 1:], q_behind[1:], atol=1e-9)
