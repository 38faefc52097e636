"""compile_program: HOME first and last, timed; load, lift and module limit from the project."""

from __future__ import annotations

import numpy as np
import pytest

from fabflow.programs.ir import Program
from fabflow.programs.motions import PTP_SPEED
from fabflow.robots import get_robot


def test_home_moves_are_first_last_and_timed(kuka_program: Program) -> None:
    robot = get_robot(kuka_program.robot)
    moves = kuka_program.moves
    home = np.radians([0, -90, 90, 0, 0, 0])
    for move in (moves[0], moves[-1]):
        assert move.joint and move.kind == "ptp" and move.blend == 0.0
        np.testing.assert_allclose(move.q, home)
        # the pose is the forward kinematics of the joint target
        T = kuka_program.T_base_world @ move.T_world_tool
        np.testing.assert_allclose(T, robot.fk(home) @ kuka_program.T_flange_tool, atol=1e-12)
    assert not any(m.joint for m in moves[1:-1])
    assert moves[0].time == 0.0
    out = np.max(np.abs(moves[1].q - home) / (robot.velocity_limits * moves[1].speed))
    assert moves[1].time == pytest.approx(out, abs=1e-6)
    back = np.max(np.abs(home - moves[-2].q) / (robot.velocity_limits * PTP_SPEED))
    before = kuka_program.instructions[-2].time
    assert moves[-1].time - before == pytest.approx(back, abs=1e-6)
    assert kuka_program.duration == moves[-1].time


def test_load_lift_and_module_limit_come_from_the_project(kuka_program: Program) -> None:
    assert kuka_program.load.mass == 8.5
    np.testing.assert_allclose(kuka_program.load.cog, [0.0, 0.01, 0.12])
    assert kuka_program.lift is not None
    assert kuka_program.lift.height == 0.35 and kuka_program.lift.axis is None
    assert kuka_program.module_motions == 1000  # the KR C4 profile
