"""Motion steps into one timed, inverse-kinematics-checked program from HOME to HOME.

:func:`compile_program` solves every waypoint of a work package's motion
(:mod:`fabflow.programs.feasibility`), keeps one arm configuration where it can
(a change goes through HOME, except on a linear move made a joint move at the
wrist singularity), times every move and attaches the program's checks
(:mod:`fabflow.programs.motion_checks`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fabflow.programs.chain_memo import ChainMemo
from fabflow.programs.feasibility import TOOL_ROTATION_SPEED, move_lengths, solve_moves
from fabflow.programs.ir import (
    Bead,
    Comment,
    GcodeOptions,
    Instruction,
    Lift,
    Load,
    Move,
    Program,
    SetOutput,
    SetPayload,
    Wait,
)
from fabflow.programs.motion_checks import configuration_of, program_checks
from fabflow.programs.motions import OUTPUTS, PTP_SPEED, Action, Step, Waypoint
from fabflow.programs.turns import settle_a1_turns
from fabflow.programs.wrist_lin import MAX_DEVIATION_DEG, MAX_JOINT_BOW
from fabflow.project import Project
from fabflow.robots.catalog import controller_profile, get_robot
from fabflow.robots.chain import RobotModel
from fabflow.tasks.targets import T_base_home_tool, home_configuration


def _drop_unreachable_optional(
    steps: Sequence[Step], robot: RobotModel, T_base_world: np.ndarray, T_flange_tool: np.ndarray
) -> list[Step]:
    """The steps without the optional via points the arm cannot reach in a
    configuration that also reaches every other target of their element (a via
    point is not worth a configuration change)."""
    waypoints = [s for s in steps if isinstance(s, Waypoint)]
    if not any(w.optional for w in waypoints):
        return list(steps)
    T = T_base_world @ np.stack([w.T_world_tool for w in waypoints]) @ np.linalg.inv(T_flange_tool)
    _, valid = robot.ik_batch(T)
    optional = np.array([w.optional for w in waypoints])
    _, owner = np.unique([w.element for w in waypoints], return_inverse=True)
    owner = owner.ravel()
    required = np.ones((owner.max() + 1, valid.shape[1]), dtype=bool)
    np.logical_and.at(required, owner[~optional], valid[~optional])
    keep = (valid & required[owner]).any(axis=1) | ~optional
    dropped = {id(w) for w, k in zip(waypoints, keep, strict=True) if not k}
    return [s for s in steps if id(s) not in dropped]


def _configurations(
    robot: RobotModel,
    q: np.ndarray,
    origin: np.ndarray,
    q_solved: np.ndarray,
    config: np.ndarray,
) -> np.ndarray:
    """:func:`~fabflow.programs.motion_checks.configuration_of` the executed moves' ``q``
    ``(n, dof)``: a move made for target ``origin[i]`` (``-1``: a HOME move) whose joint
    values are that target's solved ones ``q_solved`` to the bit has its configuration
    ``config``; only the others (HOME, an A1 turned by a whole turn) are solved again.
    A print wall has 28,000 targets."""
    out = np.full(len(q), -2, dtype=np.intp)
    own = np.flatnonzero(origin >= 0)
    same = own[(q[own] == q_solved[origin[own]]).all(axis=1)]
    out[same] = config[origin[same]]
    rest = out == -2
    if rest.any():
        out[rest] = configuration_of(robot, q[rest])
    return out


def _home_move(
    q_home: np.ndarray,
    q_from: np.ndarray,
    t: float,
    robot: RobotModel,
    T_world_tool: np.ndarray,
    label: str = "home",
) -> Move:
    """The exact PTP from ``q_from`` to HOME (tool at ``T_world_tool``), started at ``t``."""
    duration = float(np.max(np.abs(q_home - q_from) / (robot.velocity_limits * PTP_SPEED)))
    return Move(
        kind="ptp",
        T_world_tool=T_world_tool,
        q=q_home,
        speed=PTP_SPEED,
        label=label,
        time=round(t + duration, 6),
        joint=True,
    )


def compile_program(
    name: str,
    steps: Sequence[Step],
    project: Project,
    T_world_base: np.ndarray,
    header: dict[str, object],
    lift: float | None = None,
    payloads: dict[str, Load] | None = None,
    beads: dict[str, Bead] | None = None,
    memo: ChainMemo | None = None,
) -> Program:
    """Turn motion steps into a checked, timed :class:`Program` from HOME back to HOME.

    Parameters
    ----------
    name
        Program name.
    steps
        Waypoints and actions in execution order (world frame).
    project
        Robot, tool and program settings.
    T_world_base
        The station's localized robot base pose.
    header
        Header comments for the program.
    lift
        The station's lift height above its lowest position (metres), if any.
    payloads
        Element id to its load (centre of gravity in the tool frame), switched
        in when the gripper closes on it and out when it opens.
    beads
        Print path element id to its bead cross-section (what G-code extrudes).
    memo
        Chains solved by earlier compiles of the same work package, reused and
        added to (:mod:`fabflow.programs.chain_memo`).
    """
    robot = get_robot(project.robot.name)
    T_base_world = np.linalg.inv(T_world_base)
    T_flange_tool = project.robot.tool.T_flange_tool.matrix()
    q_home = home_configuration(project)
    T_world_home = T_world_base @ T_base_home_tool(project)
    steps = _drop_unreachable_optional(steps, robot, T_base_world, T_flange_tool)
    waypoints = [s for s in steps if isinstance(s, Waypoint)]
    q, via_q, via_T, slowdown, wrist, joint = solve_moves(
        waypoints, robot.name, T_base_world, T_flange_tool, q_start=q_home, q_end=q_home, memo=memo
    )
    # A change of configuration between two targets goes through HOME: a
    # joint-space swing between configurations sweeps through unknown space.
    # Not so a short linear move made a joint move through A5 = 0: its path is
    # the line's, bowed by millimetres, and checked as it is.
    config = configuration_of(robot, q)
    ptp = np.array([w.kind == "ptp" for w in waypoints], dtype=bool)
    via_home = np.r_[False, config[1:] != config[:-1]] & ptp
    q_solved = q
    q, via_q = settle_a1_turns(robot, q, via_q, ptp, q_home, via_home)
    if waypoints:
        dist, angle = move_lengths(np.stack([w.T_world_tool for w in waypoints]))
    instructions: list[Instruction] = [_home_move(q_home, q_home, 0.0, robot, T_world_home)]
    origin = [-1]  # per move, the target it goes to (-1: HOME)
    t = 0.0
    k = 0
    previous_element: str | None = None
    for step in steps:
        if step.element != previous_element:
            instructions.append(Comment(f"element {step.element}", step.element, t))
            previous_element = step.element
        if isinstance(step, Action):
            instructions.append(SetOutput(step.output, step.value, step.element, t))
            if step.dwell > 0:
                t += step.dwell
                instructions.append(Wait(step.dwell, step.element, t))
            if step.output == "gripper" and step.element in (payloads or {}):
                held = payloads[step.element] if step.value else None  # type: ignore[index]
                instructions.append(SetPayload(held, step.element, t))
            continue
        speed = step.speed / slowdown[k]
        q_from = q[k - 1] if k else q_home
        if via_home[k]:
            home = _home_move(
                q_home, q_from, t, robot, T_world_home, label="home (configuration change)"
            )
            instructions.append(home)
            origin.append(-1)
            t, q_from = home.time, q_home
        if k == 0 or step.kind == "ptp":
            duration = float(np.max(np.abs(q[k] - q_from) / (robot.velocity_limits * speed)))
        else:
            duration = max(dist[k - 1] / step.speed, angle[k - 1] / TOOL_ROTATION_SPEED)
            duration *= slowdown[k]
            if joint[k]:  # the axis speed that takes the line's time
                full = float(np.max(np.abs(q[k] - q_from) / robot.velocity_limits))
                speed = min(max(full / max(duration, 1e-9), 0.01), PTP_SPEED)
                duration = full / speed
        t += duration
        instructions.append(
            Move(
                kind="ptp" if joint[k] else step.kind,  # type: ignore[arg-type]
                T_world_tool=step.T_world_tool,
                q=q[k],
                speed=round(float(speed), 6),
                blend=step.blend,
                label=step.label,
                element=step.element,
                time=round(float(t), 6),
                via_q=via_q[k],
                via_T_world_tool=via_T[k],
                wrist_interpolated=bool(wrist[k]),
            )
        )
        origin.append(k)
        k += 1
    q_last = q[k - 1] if k else q_home
    instructions.append(_home_move(q_home, q_last, t, robot, T_world_home))
    origin.append(-1)
    checks = {}
    executed = [i for i in instructions if isinstance(i, Move)]  # HOME to HOME
    if executed:
        T_flange = T_base_world @ np.stack([m.T_world_tool for m in executed])
        T_flange = T_flange @ np.linalg.inv(T_flange_tool)
        q_executed = np.stack([m.q for m in executed])
        assert len(origin) == len(executed)
        checks = program_checks(
            robot,
            [m.kind for m in executed],
            q_executed,
            [m.via_q for m in executed],
            T_flange,
            joint=np.array([m.joint for m in executed]),
            config=_configurations(robot, q_executed, np.array(origin), q_solved, config),
        )
        checks["wrist_interpolated"] = int(wrist.sum())
        checks["joint_through_wrist"] = int(joint.sum())
        checks["changes_through_home"] = int(via_home.sum())
    if any(
        checks.get(k) for k in ("changes_inside_lin", "needless_swings", "configuration_changes")
    ):
        header = {
            **header,
            "configuration": f"{checks['configuration_changes']} changes between targets, "
            f"{checks['changes_inside_lin']} inside linear moves (A5 through 0), "
            f"{checks['needless_swings']} PTP moves swinging A1-A3 widely "
            f"({checks['avoidable_swings']} avoidable by another configuration)",
        }
    if checks.get("wrist_interpolated"):
        header = {
            **header,
            "wrist interpolated": f"{checks['wrist_interpolated']} linear moves pass the wrist "
            "singularity with the wrist axes interpolated (orientation within "
            f"{MAX_DEVIATION_DEG:g} deg, the ends exact)",
        }
    if checks.get("joint_through_wrist"):
        header = {
            **header,
            "joint moves through the wrist singularity": f"{checks['joint_through_wrist']} "
            "linear moves made joint moves: a short one takes A5 through 0 (off the line by "
            f"at most {1000 * MAX_JOINT_BOW:g} mm, orientation within {MAX_DEVIATION_DEG:g} "
            "deg, exact for a block going into its seat); the tool drawn in keeps its "
            "configuration with a half turn of A4 and A6",
        }
    slowed = slowdown > 1.0
    if slowed.any():
        header = {
            **header,
            "slowed near singularities": f"{int(slowed.sum())} linear moves, "
            f"down to {100 / slowdown.max():.0f} % of their speed",
        }
    return Program(
        name=name,
        robot=robot.name,
        T_base_world=T_base_world,
        T_flange_tool=T_flange_tool,
        instructions=tuple(instructions),
        outputs=dict(OUTPUTS),
        header=header,
        tool_name=project.robot.tool.name,
        checks=checks,
        load=Load(project.robot.tool.mass, np.asarray(project.robot.tool.cog, dtype=float)),
        lift=None if lift is None else Lift(lift, project.robot.platform.lift_axis),
        module_motions=project.program.module_motions
        or controller_profile(project.robot.name, project.program.controller).module_motions,
        beads=dict(beads or {}),
        gcode=GcodeOptions(project.program.gcode.flavor, project.program.gcode.filament_diameter),
    )
