"""The ``project`` stage of ``fabflow build``: the validated project as ``project.json``."""

from __future__ import annotations

from fabflow.build.context import BuildContext
from fabflow.output import write_json
from fabflow.version import __version__


def stage_project(ctx: BuildContext) -> None:
    """Write the validated project, defaults filled in, as ``project.json``."""
    p = ctx.project
    write_json(
        ctx.out / "project.json",
        {"fabflow_version": __version__, "project": p.model_dump(mode="json")},
    )
    ctx.add("project", "name", p.name)
    ctx.add("project", "robot", p.robot.name)
    if p.stone_wall() is None:
        ctx.add("project", "localization", p.localization.method)
    else:
        ctx.add("project", "localization", "none: the machine stands still, stones are scanned")
    ctx.add("project", "element sources", len(p.elements))
