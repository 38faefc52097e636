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
from fabflow.errors import LocalizationError
from fabflow.positioning.result import BasePose
from fabflow.programs.feasibility import TOOL_ROTATION_SPEED, move_lengths, solve_moves
from fabflow.programs.ir import Comment, Instruction, Move, Program, SetOutput, Wait
from fabflow.programs.motion_checks import program_checks
from fabflow.programs.motions import OUTPUTS, Action, Step, Waypoint, work_package_motion
from fabflow.programs.wrist_lin import MAX_DEVIATION_DEG
from fabflow.programs.writers import writer_for
from fabflow.project import Project
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.tasks.plan import Plan, WorkPackage
from fabflow.version import __version__


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
    q, via_q, via_T, slowdown, wrist = solve_moves(
        waypoints, robot.name, T_base_world, T_flange_tool
    )
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
                wrist_interpolated=bool(wrist[k]),
            )
        )
        k += 1
    checks = {}
    if waypoints:
        T_flange = T_base_world @ np.stack([w.T_world_tool for w in waypoints])
        T_flange = T_flange @ np.linalg.inv(T_flange_tool)
        checks = program_checks(robot, [w.kind for w in waypoints], q, via_q, T_flange)
        checks["wrist_interpolated"] = int(wrist.sum())
    if checks.get("changes_inside_lin") or checks.get("needless_swings"):
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
    )


def program_name(wp: WorkPackage) -> str:
    """Program name of a work package: visit number and station."""
    return f"fab_v{wp.index + 1:02d}_{wp.station.id}"


def work_package_program(
    wp: WorkPackage,
    elements_by_id: dict[str, Element],
    project: Project,
    base_pose: BasePose,
) -> Program:
    """The checked program of one work package, in the station's localized base frame."""
    elements = [elements_by_id[e] for e in wp.elements]
    T_world_base = np.asarray(base_pose.T_world_base, dtype=float)
    steps = work_package_motion(elements, project, T_world_base)
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
    return compile_program(program_name(wp), steps, project, T_world_base, header)


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
    for wp in plan.work_packages:
        if not wp.elements or wp.index not in base_poses:
            continue
        pose = base_poses[wp.index]
        if pose.integrity is None or pose.integrity.failed:
            why = "it was not tested" if pose.integrity is None else pose.integrity.reason
            raise LocalizationError(
                f"work package {wp.index + 1} (station {wp.station.id}): no program from a "
                f"base pose that failed its integrity tests: {why}"
            )
        program = work_package_program(wp, by_id, project, pose)
        programs.append(program)
        files.update(writer.write(program))
    return programs, files
