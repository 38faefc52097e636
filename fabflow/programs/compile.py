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

from fabflow.design.elements import Element, structure_timeline
from fabflow.design.specs import PrintPathSpec
from fabflow.errors import LocalizationError
from fabflow.positioning.result import BasePose
from fabflow.programs.assemble import compile_program
from fabflow.programs.ir import Bead, Load, Program
from fabflow.programs.motions import work_package_motion
from fabflow.programs.replan import checked_program, replanned_program, with_contacts
from fabflow.programs.writers import writer_for
from fabflow.project import Project
from fabflow.tasks.plan import Plan, WorkPackage
from fabflow.tasks.split import with_pieces
from fabflow.tasks.targets import element_tool_frames
from fabflow.version import __version__


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


def element_beads(elements: Sequence[Element]) -> dict[str, Bead]:
    """The bead cross-section of every print path element, by id (metres).

    From the element's ``bead_width`` and ``layer_height`` attributes; one without
    them gets :class:`~fabflow.design.specs.PrintPathSpec`'s defaults.
    """
    fields = PrintPathSpec.model_fields
    width, height = fields["bead_width"].default, fields["layer_height"].default
    return {
        e.id: Bead(
            float(e.attributes.get("bead_width", width)),
            float(e.attributes.get("layer_height", height)),
        )
        for e in elements
        if e.type == "print_path"
    }


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
    coming: Sequence[tuple[Element, int]] = (),
) -> Program:
    """The checked program of one work package, in the station's localized base frame.

    ``built`` are the elements standing when it starts (pre-built ones and those
    of earlier work packages) and ``coming`` the hand-built ones that come
    during it (:func:`fabflow.design.elements.structure_timeline`): the
    collision check (:func:`checked_program`) keeps the arm clear of them.
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
    if coming:
        first, after = min(coming, key=lambda c: c[1])
        header["hand work"] = (
            f"{len(coming)} pre-built elements come during this program, each set by hand "
            f"once what it rests on stands and the tool has left (the first, {first.id}, "
            f"after {elements[after].id}); the collision check assumes so"
        )
    options = {
        "lift": wp.station.lift,
        "payloads": element_payloads(elements),
        "beads": element_beads(elements),
    }
    if not project.program.check_collisions:
        steps = work_package_motion(elements, project, T_world_base)
        return compile_program(name, steps, project, T_world_base, header, **options)
    if project.program.check_collisions == "report":
        program, contacts = replanned_program(
            name, elements, built, project, T_world_base, header, coming=coming, **options
        )
        return with_contacts(program, contacts, project.program.clearance)
    return checked_program(
        name, elements, built, project, T_world_base, header, coming=coming, **options
    )


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
        All elements of the project, as designed or with the plan's print path
        pieces in place of their parents (applied here when needed).
    project
        The project (robot, tool, program settings).
    base_poses
        Localized base pose per visit (``WorkPackage.index``); a work package
        without one gets no program (a visit whose localization failed).
    fmt
        ``krl``, ``rapid``, ``urscript``, ``json`` or ``gcode`` (default: the project's
        format).

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
    writer = writer_for(fmt, project.robot.name)
    elements = with_pieces(elements, plan.split_elements)
    by_id = {e.id: e for e in elements}
    programs: list[Program] = []
    files: dict[str, str] = {}
    timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
    for wp, (built, coming) in zip(plan.work_packages, timeline, strict=True):
        if not wp.elements or wp.index not in base_poses:
            continue
        pose = base_poses[wp.index]
        if pose.integrity is None or pose.integrity.failed:
            why = "it was not tested" if pose.integrity is None else pose.integrity.reason
            raise LocalizationError(
                f"work package {wp.index + 1} (station {wp.station.id}): no program from a "
                f"base pose that failed its integrity tests: {why}"
            )
        program = work_package_program(wp, by_id, project, pose, built, coming)
        programs.append(program)
        files.update(writer.write(program))
    return programs, files
