"""The build runner: every stage, in order, into one output folder.

Each stage lives in its own module of this package (``project``, ``design``,
``plan``, ``localize``, ``program``, ``preview``; ``stones`` for a stone wall) and shares a typed
:class:`~fabflow.build.context.BuildContext`. :func:`run_build` runs the stages
into a staging folder and moves it into place only when all have completed.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from fabflow.build.context import BuildContext, Stage
from fabflow.build.design import stage_design
from fabflow.build.localize import stage_localize
from fabflow.build.plan import stage_plan
from fabflow.build.preview import stage_preview
from fabflow.build.program import stage_program
from fabflow.build.project import stage_project
from fabflow.build.stones import stage_stone_preview, stage_stone_programs, stage_stones
from fabflow.output import atomic_output_dir, write_json
from fabflow.project import Project


def stages(project: Project | None = None) -> list[tuple[str, Stage]]:
    """The stages of ``fabflow build`` for ``project``, in order.

    A stone wall is built from found stones: no stations to plan nor base to
    localize (the machine stands still), one program per stone.
    """
    if project is not None and project.stone_wall() is not None:
        return [
            ("project", stage_project),
            ("design", stage_design),
            ("stones", stage_stones),
            ("program", stage_stone_programs),
            ("preview", stage_stone_preview),
        ]
    return [
        ("project", stage_project),
        ("design", stage_design),
        ("plan", stage_plan),
        ("localize", stage_localize),
        ("program", stage_program),
        ("preview", stage_preview),
    ]


def run_build(
    project: Project,
    out: str | Path,
    on_stage: Callable[[str], None] | None = None,
    until: str | None = None,
) -> BuildContext:
    """Run the stages for ``project`` and move the results into ``out`` atomically.

    Parameters
    ----------
    project
        The validated project.
    out
        Destination folder; replaced as a whole only if every stage succeeds.
    on_stage
        Called with each stage's name before it runs (progress reporting).
    until
        Name of the last stage to run (default: all stages).
    """
    selected = stages(project)
    if until is not None:
        names = [name for name, _ in selected]
        selected = selected[: names.index(until) + 1]
    with atomic_output_dir(out) as staging:
        ctx = BuildContext(project=project, out=staging)
        for name, stage in selected:
            if on_stage is not None:
                on_stage(name)
            stage(ctx)
        ctx.finish()
        write_json(
            staging / "summary.json",
            [{"stage": s, "item": i, "value": v} for s, i, v in ctx.summary],
        )
    ctx.out = Path(out)
    return ctx
