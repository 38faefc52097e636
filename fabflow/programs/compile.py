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

import numpy as np

from fabflow.design.elements import Element
from fabflow.errors import InfeasibleError, LocalizationError
from fabflow.positioning.result import BasePose
from fabflow.programs.collision import Contact, check_package
from fabflow.programs.collision_model import environment, safe_heights
from fabflow.programs.feasibility import TOOL_ROTATION_SPEED, move_lengths, solve_moves
from fabflow.programs.ir import Comment, Instruction, Move, Program, SetOutput, Wait
from fabflow.programs.motions import (
    OUTPUTS,
    Action,
    Step,
    T_base_pick_tool,
    Waypoint,
    work_package_motion,
)
from fabflow.programs.writers import writer_for
from fabflow.project import Project
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.tasks.plan import Plan, WorkPackage
from fabflow.version import __version__

SAFE_WIDTH = 0.5
"""Plan distance from the line magazine - place within which the structure sets the
safe height of a re-planned block (metres): the arm's forearm and wrist pass there."""


def _drop_unreachable_optional(
    steps: Sequence[Step], robot: RobotModel, T_base_world: np.ndarray, T_flange_tool: np.ndarray
) -> list[Step]:
    """The steps without the optional via points the arm cannot reach."""
    optional = [s for s in steps if isinstance(s, Waypoint) and s.optional]
    if not optional:
        return list(steps)
    T = T_base_world @ np.stack([w.T_world_tool for w in optional]) @ np.linalg.inv(T_flange_tool)
    _, valid = robot.ik_batch(T)
    dropped = {id(w) for w, ok in zip(optional, valid.any(axis=1), strict=True) if not ok}
    return [s for s in steps if id(s) not in dropped]


def compile_program(
    name: str,
    steps: Sequence[Step],
    project: Project,
    T_world_base: np.ndarray,
    header: dict[str, object],
) -> Program:
    """Turn motion steps into a checked, timed :class:`Program`.

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
    """
    robot = get_robot(project.robot.model)
    T_base_world = np.linalg.inv(T_world_base)
    T_flange_tool = project.robot.tool.T_flange_tool.matrix()
    steps = _drop_unreachable_optional(steps, robot, T_base_world, T_flange_tool)
    waypoints = [s for s in steps if isinstance(s, Waypoint)]
    q, via_q, via_T, slowdown = solve_moves(waypoints, robot.name, T_base_world, T_flange_tool)
    if waypoints:
        dist, angle = move_lengths(np.stack([w.T_world_tool for w in waypoints]))
    instructions: list[Instruction] = []
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
            continue
        speed = step.speed / slowdown[k]
        if k == 0:
            duration = 0.0
        elif step.kind == "ptp":
            duration = float(np.max(np.abs(q[k] - q[k - 1]) / (robot.velocity_limits * speed)))
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
            )
        )
        k += 1
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
    )


def program_name(wp: WorkPackage) -> str:
    """Program name of a work package: visit number and station."""
    return f"fab_v{wp.index + 1:02d}_{wp.station.id}"


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
        "generator": f"fabflow {__version__}",
    }
    if not project.program.check_collisions:
        steps = work_package_motion(elements, project, T_world_base)
        return compile_program(name, steps, project, T_world_base, header)
    return checked_program(name, elements, built, project, T_world_base, header)


def checked_program(
    name: str,
    elements: Sequence[Element],
    built: Sequence[Element],
    project: Project,
    T_world_base: np.ndarray,
    header: dict[str, object],
) -> Program:
    """Compile a work package and check it for collisions; re-plan what collides.

    The elements whose moves come closer than ``program.clearance`` to an
    obstacle (:mod:`fabflow.programs.collision`), and the element before each
    (whose retract the next pick approach starts from), are re-planned over the
    structure (:func:`fabflow.programs.motions.element_motion` with a safe
    height); a collision that remains is an :class:`InfeasibleError` naming the
    element, the move, the body and the penetration.
    """
    program, contacts = replanned_program(name, elements, built, project, T_world_base, header)
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
) -> tuple[Program, list[Contact]]:
    """:func:`checked_program` without the error: the program and its remaining contacts."""
    steps = work_package_motion(elements, project, T_world_base)
    program = compile_program(name, steps, project, T_world_base, header)
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
        program = compile_program(name, steps, project, T_world_base, header)
        contacts = check_package(program, project, obstacles, elements)
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
