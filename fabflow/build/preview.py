"""The ``preview`` stage of ``fabflow build``: ``OUT/preview.html``."""

from __future__ import annotations

from fabflow.build.context import BuildContext
from fabflow.preview.export import export_html
from fabflow.preview.inputs import model_for_project


def stage_preview(ctx: BuildContext) -> None:
    """Export the construction sequence as ``preview.html`` (one offline HTML file).

    Reads the elements, the plan and, when present, the localized base poses;
    sets ``ctx.preview``.
    """
    localization = {int(i): value[0] for i, value in (ctx.localization or {}).items()}
    model = model_for_project(
        ctx.project, ctx.need_elements(), ctx.need_plan(), localization=localization
    )
    result = export_html(model, ctx.out / "preview.html", ctx.project)
    ctx.preview = result
    ctx.add("preview", "file", f"preview.html ({result.size_bytes / 1e6:.1f} MB)")
    ctx.add("preview", "steps", f"{result.n_steps} (plays {result.duration_s:.0f} s)")
