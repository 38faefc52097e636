"""What ``fabflow preview`` does: load, plan, then serve the scene or export it."""

from __future__ import annotations

import io
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from fabflow.design.elements import Element
from fabflow.design.generate import generate_elements
from fabflow.errors import InputError
from fabflow.positioning.result import BasePose
from fabflow.preview.app import serve
from fabflow.preview.export import check_export_target, export_html
from fabflow.preview.gui import ProgramSource
from fabflow.preview.inputs import model_for_project, read_build_outputs
from fabflow.preview.model import COLOUR_MODES, PreviewModel
from fabflow.preview.stones import export_stone_html
from fabflow.programs.compile import work_package_program
from fabflow.programs.writers import writer_for
from fabflow.project import Project, load_project
from fabflow.stones.run import run_stone_wall
from fabflow.tasks.plan import Plan
from fabflow.tasks.planner import plan_project
from fabflow.tasks.split import with_pieces


def project_program_source(
    project: Project, elements: list[Element], plan: Plan, model: PreviewModel
) -> ProgramSource:
    """The download button's programs: the project's own writer, per work package.

    The program is compiled (with its inverse-kinematics checks) when it is
    asked for, in the project's program format, in the station's localized base
    frame when the model holds a localization result for the visit, else the planned
    one. A format that writes several files (KRL ``.src`` + ``.dat``) comes as
    a zip. ``elements`` are the design's; the pieces of print paths that the plan
    split are taken from the plan.
    """

    by_id = {e.id: e for e in with_pieces(elements, plan.split_elements)}

    def source(package: int) -> tuple[str, bytes]:
        wp = plan.work_packages[package]
        base_pose = model.localization_at(package) or BasePose(
            T_world_base=model.T_world_base[package],
            covariance=np.zeros((6, 6)),
            method="planned",
            station=wp.station.id,
        )
        program = work_package_program(wp, by_id, project, base_pose)
        files = writer_for(project.program.format, project.robot.name).write(program)
        if len(files) == 1:
            name, text = next(iter(files.items()))
            return name, text.encode()
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
            for name, text in sorted(files.items()):
                zf.writestr(name, text)
        return f"{program.name}.zip", buf.getvalue()

    return source


def check_colour_mode(colour_by: str | None, sim: Path | None) -> None:
    """Reject an unknown colour mode, or ``deviation`` without simulation results."""
    if colour_by is None:
        return
    if colour_by not in COLOUR_MODES:
        raise InputError(f"--colour-by must be one of {', '.join(COLOUR_MODES)}, got '{colour_by}'")
    if colour_by == "deviation" and sim is None:
        raise InputError("--colour-by deviation needs simulation results: pass --sim DIR")


def _export_stone_wall(
    project: Project,
    export: Path | None,
    colour_by: str | None,
    sim: Path | None,
    say: Callable[[str], None],
) -> None:
    """A stone wall's preview: the simulated run, exported as one HTML file."""
    where = "elements[0].stone_wall"
    if export is None:
        raise InputError(
            "a stone wall's preview is one HTML file of a simulated run: pass --export "
            "FILE.html ('fabflow build' writes it as preview.html)",
            project.path,
            where,
        )
    if sim is not None or colour_by is not None:
        raise InputError(
            "--sim and --colour-by apply to designed elements, not to a stone wall",
            project.path,
            where,
        )

    say(f"building the stone wall of '{project.name}' in simulation")
    result = export_stone_html(run_stone_wall(project), export, project)
    say(
        f"wrote {result.path.resolve()} ({result.size_bytes / 1e6:.1f} MB, "
        f"{result.n_steps} steps, plays {result.duration_s:.0f} s)"
    )


def run_preview(
    project_path: Path,
    port: int = 8080,
    host: str = "127.0.0.1",
    export: Path | None = None,
    colour_by: str | None = None,
    sim: Path | None = None,
    say: Callable[[str], None] = print,
    wait: Callable[[], None] | None = None,
) -> None:
    """Load a project, plan it and show it live, or export it as one HTML file.

    A stone wall has no stations to plan: its preview is the simulated build,
    exported only (``export`` required, ``colour_by`` and ``sim`` refused).

    Parameters
    ----------
    project_path
        Project YAML file or folder.
    port, host
        Where the live server listens (the next free port if ``port`` is busy).
    export
        Write this HTML file instead of serving.
    colour_by
        Colour mode; ``station`` live and ``state`` in an export if ``None``.
    sim
        A ``fabflow simulate`` output folder (deviations, localization results) or
        a ``fabflow build`` output folder (localization results).
    say
        Prints progress and the address.
    wait
        Blocks while the live preview runs (default: until Ctrl-C).
    """

    check_colour_mode(colour_by, sim)
    if export is not None:
        check_export_target(export)
    project = load_project(project_path)
    if project.stone_wall() is not None:
        _export_stone_wall(project, export, colour_by, sim, say)
        return
    elements, plan = read_build_outputs(sim) if sim is not None else (None, None)
    if plan is None or elements is None:
        elements = generate_elements(project.elements, project.path, project.limits)
        plan = plan_project(project, elements)
    model = model_for_project(project, elements, plan, sim_dir=sim)
    if colour_by == "deviation" and model.deviation is None:
        raise InputError(
            "--colour-by deviation needs a per-element deviation table (a fabflow simulate "
            "output folder); this folder has localization results only",
            source=sim,
        )
    if export is not None:
        result = export_html(model, export, project, colour_mode=colour_by or "state")
        say(
            f"wrote {result.path.resolve()} ({result.size_bytes / 1e6:.1f} MB, "
            f"{result.n_steps} steps, plays {result.duration_s:.0f} s)"
        )
        return

    live = serve(
        model,
        project,
        host=host,
        port=port,
        colour_mode=colour_by or "station",
        program_source=project_program_source(project, elements, plan, model),
    )
    say(f"preview of '{project.name}' at {live.url} (Ctrl-C to stop)")
    try:
        if wait is not None:
            wait()
        else:
            while True:
                time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        live.stop()
