"""The build pipeline: every stage that exists, run in order into one output folder.

A stage is a function ``stage(ctx) -> None`` that reads the project and the
results of earlier stages from ``ctx.results``, writes its files under
``ctx.out`` and adds rows to ``ctx.summary``. :func:`run_build` runs the stages
into a staging folder and moves it into place only when all have completed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fabflow import __version__
from fabflow.build.design import stage_design
from fabflow.build.plan import stage_plan
from fabflow.build.preview import stage_preview
from fabflow.localize.plan import stage_localize
from fabflow.output import atomic_output_dir, write_json
from fabflow.programs.compile import stage_program
from fabflow.project import Project


@dataclass
class BuildContext:
    """What the stages of one build share.

    Attributes
    ----------
    project
        The validated project.
    out
        The staging folder stages write into (moved to the real output at the end).
    results
        Results of earlier stages by stage name (plain data and numpy arrays).
    summary
        Rows ``(stage, item, value)`` for the summary table.
    """

    project: Project
    out: Path
    results: dict[str, Any] = field(default_factory=dict)
    summary: list[tuple[str, str, str]] = field(default_factory=list)

    def add(self, stage: str, item: str, value: object) -> None:
        """Add one row to the build summary."""
        self.summary.append((stage, item, str(value)))


Stage = Callable[[BuildContext], None]


def stage_project(ctx: BuildContext) -> None:
    """Write the validated project, defaults filled in, as ``project.json``."""
    p = ctx.project
    write_json(
        ctx.out / "project.json",
        {"fabflow_version": __version__, "project": p.model_dump(mode="json")},
    )
    ctx.add("project", "name", p.name)
    ctx.add("project", "robot", p.robot.model)
    ctx.add("project", "localization", p.localization.method)
    ctx.add("project", "element sources", len(p.elements))


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
