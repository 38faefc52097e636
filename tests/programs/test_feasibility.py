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
