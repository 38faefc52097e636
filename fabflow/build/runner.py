"""The build runner: every stage, in order, into one output folder.

Each stage lives in its own module of this package (``project``, ``design``,
``plan``, ``localize``, ``program``, ``preview``) and shares a typed
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
from fabflow.output import atomic_output_dir, write_json
from fabflow.project import Project


def stages() -> list[tuple[str, Stage]]:
    """The stages of ``fabflow build``, in order."""
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
    selected = stages()
    if until is not None:
        names = [name for name, _ in selected]
        selected = selected[: names.index(until) + 1]
    with atomic_output_dir(out) as staging:
        ctx = BuildContext(project=project, out=staging)
        for name, stage in selected:
            if on_stage is not None:
                on_stage(name)
            stage(ctx)
        write_json(
            staging / "summary.json",
            [{"stage": s, "item": i, "value": v} for s, i, v in ctx.summary],
        )
    ctx.out = Path(out)
    return ctx
