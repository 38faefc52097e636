"""One program per stone: approach, grasp, lift, carry, set down in the slot, release.

The moves go through :func:`fabflow.programs.assemble.compile_program`, as every
work package's do: each target is solved with the machine's inverse kinematics,
the linear moves are followed one controller step at a time, the program runs
from HOME to HOME and carries its configuration checks. The gripper approaches
the grasp along its own z (the direction the grasp planner tested free of the
cloud) and backs out the same way after the release; the held stone is lifted
and lowered vertically.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from fabflow.manipulation.objects import FoundObject
from fabflow.programs.assemble import compile_program
from fabflow.programs.ir import Load, Program
from fabflow.programs.motions import GRIP_DWELL_S, PTP_SPEED, Action, Step, Waypoint
from fabflow.project import Project
from fabflow.stones.placing import STONE_DENSITY, backed_off, raised, stone_mass
from fabflow.stones.run import CLEARANCE, PickResult
from fabflow.transforms.se3 import inv_T

FloatArray = NDArray[np.float64]


def pick_steps(pick: PickResult, speed: float) -> list[Step]:
    """The waypoints and gripper actions of one pick and place (world frame).

    Parameters
    ----------
    pick
        A pick with a grasp and a release.
    speed
        Linear speed (m/s).
    """
    assert pick.T_grasp is not None and pick.T_release is not None
    G, R, sid = pick.T_grasp, pick.T_release, pick.slot
    return [
        Waypoint("ptp", backed_off(G, CLEARANCE), PTP_SPEED, 0.0, "grasp approach", sid),
        Waypoint("lin", G, speed, 0.0, "grasp", sid),
        Action("gripper", True, GRIP_DWELL_S, sid),
        Waypoint("lin", raised(G, CLEARANCE), speed, 0.0, "lift", sid),
        Waypoint("ptp", raised(R, CLEARANCE), PTP_SPEED, 0.0, "release approach", sid),
        Waypoint("lin", R, speed, 0.0, "release", sid, seated=True),
        Action("gripper", False, GRIP_DWELL_S, sid),
        Waypoint("lin", backed_off(R, CLEARANCE), speed, 0.0, "retract", sid),
    ]


def pick_program(
    project: Project, pick: PickResult, obj: FoundObject, T_world_base: FloatArray, index: int
) -> Program:
    """The checked program of one pick and place, HOME to HOME.

    Parameters
    ----------
    project
        The project (robot, tool, program settings).
    pick
        The pick (grasp and release poses, world frame).
    obj
        The object (its model's hull gives the mass; its centroid at the grasp,
        ``pick.T_object``, the centre of gravity).
    T_world_base
        The machine's base pose (world).
    index
        Position of the pick in the wall (names the program).
    """
    assert pick.T_grasp is not None and pick.T_object is not None
    cog = (inv_T(pick.T_grasp) @ pick.T_object[:, 3])[:3]
    header: dict[str, object] = {
        "project": project.name,
        "slot": pick.slot,
        "object": obj.id,
        "stone mass": f"{stone_mass(obj):.0f} kg (model hull x {STONE_DENSITY:g} kg/m^3)",
        "grasp opening": f"{pick.opening:.3f} m",
    }
    return compile_program(
        f"stone_{index + 1:02d}_{pick.slot}",
        pick_steps(pick, project.program.speed),
        project,
        T_world_base,
        header,
        payloads={pick.slot: Load(stone_mass(obj), cog)},
    )
