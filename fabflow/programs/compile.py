"""Robot programs per work package: motion steps compiled into checked, timed programs.

:func:`work_package_program` turns the motion of one work package
(:mod:`fabflow.programs.motions`) into a :class:`~fabflow.programs.ir.Program`
in the station's localized base frame, with every move checked by
:mod:`fabflow.programs.feasibility`; :func:`write_programs` does so for a whole
plan and renders the files with the project's writer
(:mod:`fabflow.programs.writers`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fabflow.design.elements import Element
from fabflow.errors import InfeasibleError, LocalizationError
from fabflow.positioning.result import BasePose
from fabflow.programs.collision import Contact, check_package
from fabflow.programs.collision_model import environment, safe_heights
from fabflow.programs.feasibility import TOOL_ROTATION_SPEED, move_lengths, solve_moves
from fabflow.programs.ir import (
    Comment,
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
from fabflow.programs.motions import (
    OUTPUTS,
    PTP_SPEED,
    Action,
    Step,
    T_base_pick_tool,
    Waypoint,
    work_package_motion,
)
from fabflow.programs.wrist_lin import MAX_DEVIATION_DEG
from fabflow.programs.writers import writer_for
from fabflow.project import Project
from fabflow.robots.catalog import controller_profile, get_robot
from fabflow.robots.chain import RobotModel
from fabflow.tasks.plan import Plan, WorkPackage
from fabflow.tasks.targets import element_tool_frames
from fabflow.version import __version__

SAFE_WIDTH = 0.5
"""Plan distance from the line magazine - place within which the structure sets the
safe height of a re-planned block (metres): the arm's forearm and wrist pass there."""


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


def home_configuration(project: Project) -> np.ndarray:
    """The HOME joint configuration (radians): ``robot.home_deg`` or the catalogue's."""
    robot = get_robot(project.robot.model)
    if project.robot.home_deg is not None:
        return np.radians(np.asarray(project.robot.home_deg, dtype=float))
    return np.asarray(robot.q_home, dtype=float)


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
    """
    robot = get_robot(project.robot.model)
    T_base_world = np.linalg.inv(T_world_base)
    T_flange_tool = project.robot.tool.T_flange_tool.matrix()
    q_home = home_configuration(project)
    T_world_home = T_world_base @ robot.fk(q_home) @ T_flange_tool
    steps = _drop_unreachable_optional(steps, robot, T_base_world, T_flange_tool)
    waypoints = [s for s in steps if isinstance(s, Waypoint)]
    q, via_q, via_T, slowdown, wrist = solve_moves(
        waypoints, robot.name, T_base_world, T_flange_tool, q_start=q_home
    )
    # A change of configuration between two targets goes through HOME: a
    # joint-space swing between configurations sweeps through unknown space.
    config = configuration_of(robot, q)
    ptp = np.array([w.kind == "ptp" for w in waypoints], dtype=bool)
    via_home = np.r_[False, config[1:] != config[:-1]] & ptp
    if waypoints:
        dist, angle = move_lengths(np.stack([w.T_world_tool for w in waypoints]))
    instructions: list[Instruction] = [_home_move(q_home, q_home, 0.0, robot, T_world_home)]
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
            t, q_from = home.time, q_home
        if k == 0 or step.kind == "ptp":
            duration = float(np.max(np.abs(q[k] - q_from) / (robot.velocity_limits * speed)))
        else:
            duration = max(dist[k - 1] / step.speed, angle[k - 1] / TOOL_ROTATION_SPEED)
            duration *= slowdown[k]
        t += duration
        instructions.append(
            Move(
                kind=step.kind,  # type: ignore[arg-type]
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
        k += 1
    q_last = q[k - 1] if k else q_home
    instructions.append(_home_move(q_home, q_last, t, robot, T_world_home))
    checks = {}
    executed = [i for i in instructions if isinstance(i, Move)]  # HOME to HOME
    if executed:
        T_flange = T_base_world @ np.stack([m.T_world_tool for m in executed])
        T_flange = T_flange @ np.linalg.inv(T_flange_tool)
        checks = program_checks(
            robot,
            [m.kind for m in executed],
            np.stack([m.q for m in executed]),
            [m.via_q for m in executed],
            T_flange,
            joint=np.array([m.joint for m in executed]),
        )
        checks["wrist_interpolated"] = int(wrist.sum())
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
        or controller_profile(project.robot.model, project.program.controller).module_motions,
    )


def program_name(wp: WorkPackage) -> str:
    """Program name of a work package: visit number and station."""
    return f"fab_v{wp.index + 1:02d}_{wp.station.id}"


def element_payloads(elements: Sequence[Element]) -> dict[str, Load]:
    """The load of every gripped element with a ``mass`` attribute (kg).

    Its centre of gravity is the element's centre in the tool frame at its place
    pose (the tool holds it the same way from pick to place).
    """
    held = [e for e in elements if e.type == "block" and "mass" in e.attributes]
    loads = {}
    for e in held:
        T_world_tool = element_tool_frames(e)[0]
        cog = np.linalg.solve(T_world_tool, np.append(e.T_world_element[:3, 3], 1.0))[:3]
        loads[e.id] = Load(float(e.attributes["mass"]), cog)
    return loads


def _load_note(project: Project) -> str:
    """The tool load for the header, flagged when the project left it at the default."""
    tool = project.robot.tool
    cog = ", ".join(f"{v * 1000:.0f}" for v in tool.cog)
    note = f"{tool.mass:g} kg, centre of gravity ({cog}) mm in the flange frame"
    if "mass" not in tool.model_fields_set:
        note += " (the default: set robot.tool.mass and cog for the real tool)"
    return note


def work_package_program(
    wp: WorkPackage,
    elements_by_id: dict[str, Element],
    project: Project,
    base_pose: BasePose,
    built: Sequence[Element] = (),
) -> Program:
    """The checked program of one work package, in the station's localized base frame.

    ``built`` are the elements standing when it starts (pre-built ones and those
    of earlier work packages): the collision check (:func:`checked_program`)
    keeps the arm clear of them.
    """
    elements = [elements_by_id[e] for e in wp.elements]
    T_world_base = np.asarray(base_pose.T_world_base, dtype=float)
    name = program_name(wp)
    header: dict[str, object] = {
        "project": project.name,
        "station": wp.station.id,
        "visit": wp.index + 1,
        "elements": f"{wp.elements[0]}..{wp.elements[-1]} ({len(wp.elements)})"
        if wp.elements
        else "none",
        "localization": f"{base_pose.method}, rmse {base_pose.rmse * 1000:.2f} mm",
        "lift": f"{wp.station.lift * 1000:.0f} mm above its lowest position",
        "tool load": _load_note(project),
        "generator": f"fabflow {__version__}",
    }
    options = {"lift": wp.station.lift, "payloads": element_payloads(elements)}
    if not project.program.check_collisions:
        steps = work_package_motion(elements, project, T_world_base)
        return compile_program(name, steps, project, T_world_base, header, **options)
    return checked_program(name, elements, built, project, T_world_base, header, **options)


def checked_program(
    name: str,
    elements: Sequence[Element],
    built: Sequence[Element],
    project: Project,
    T_world_base: np.ndarray,
    header: dict[str, object],
    **options: Any,
) -> Program:
    """Compile a work package and check it for collisions; re-plan what collides.

    The elements whose moves come closer than ``program.clearance`` to an
    obstacle (:mod:`fabflow.programs.collision`), and the element before each
    (whose retract the next pick approach starts from), are re-planned over the
    structure (:func:`fabflow.programs.motions.element_motion` with a safe
    height); a collision that remains is an :class:`InfeasibleError` naming the
    element, the move, the body and the penetration. ``options`` go to
    :func:`compile_program` (lift, payloads).
    """
    program, contacts = replanned_program(
        name, elements, built, project, T_world_base, header, **options
    )
    if contacts:
        worst = min(contacts, key=lambda c: c.distance)
        raise InfeasibleError(
            f"program {name}: {len(contacts)} collision(s) at "
            f"{project.program.clearance * 1000:g} mm clearance; the worst: {worst.describe()}"
        )
    return program


def replanned_program(
    name: str,
    elements: Sequence[Element],
    built: Sequence[Element],
    project: Project,
    T_world_base: np.ndarray,
    header: dict[str, object],
    **options: Any,
) -> tuple[Program, list[Contact]]:
    """:func:`checked_program` without the error: the program and its remaining contacts."""
    steps = work_package_motion(elements, project, T_world_base)
    program = compile_program(name, steps, project, T_world_base, header, **options)
    obstacles = environment(project, T_world_base, built, elements)
    contacts = check_package(program, project, obstacles, elements)
    if contacts:
        index = {e.id: j for j, e in enumerate(elements)}
        hit = {index[c.element] for c in contacts if c.element in index}
        hit |= {j - 1 for j in hit if j > 0}
        T_world_pick = T_world_base @ T_base_pick_tool(project)
        heights = safe_heights(
            obstacles, elements, T_world_pick, project.program.clearance, SAFE_WIDTH
        )
        safe = {elements[j].id: heights[elements[j].id] for j in hit if elements[j].id in heights}
        steps = work_package_motion(elements, project, T_world_base, safe)
        try:
            again = compile_program(name, steps, project, T_world_base, header, **options)
        except InfeasibleError:
            return program, contacts  # the safe height is out of reach: report the collisions
        program, contacts = again, check_package(again, project, obstacles, elements)
    return program, contacts


def write_programs(
    plan: Plan,
    elements: Sequence[Element],
    project: Project,
    base_poses: dict[int, BasePose],
    fmt: str | None = None,
) -> tuple[list[Program], dict[str, str]]:
    """Programs for every work package and their files.

    Parameters
    ----------
    plan
        The plan (work packages in order).
    elements
        All elements of the project.
    project
        The project (robot, tool, program settings).
    base_poses
        Localized base pose per visit (``WorkPackage.index``); a work package
        without one gets no program (a visit whose localization failed).
    fmt
        ``krl``, ``rapid``, ``urscript`` or ``json`` (default: the project's format).

    Returns
    -------
    programs, files
        The programs and a mapping of file name to text (all packages).

    Raises
    ------
    LocalizationError
        When a given base pose failed its integrity tests (or was never tested):
        no program is written from it.
    """
    fmt = fmt or project.program.format
    writer = writer_for(fmt, project.robot.model)
    by_id = {e.id: e for e in elements}
    programs: list[Program] = []
    files: dict[str, str] = {}
    built = [e for e in elements if not e.robot_built]
    for wp in plan.work_packages:
        if not wp.elements or wp.index not in base_poses:
            built += [by_id[e] for e in wp.elements]
            continue
        pose = base_poses[wp.index]
        if pose.integrity is None or pose.integrity.failed:
            why = "it was not tested" if pose.integrity is None else pose.integrity.reason
            raise LocalizationError(
                f"work package {wp.index + 1} (station {wp.station.id}): no program from a "
                f"base pose that failed its integrity tests: {why}"
            )
        program = work_package_program(wp, by_id, project, pose, built)
        built += [by_id[e] for e in wp.elements]
        programs.append(program)
        files.update(writer.write(program))
    return programs, files
