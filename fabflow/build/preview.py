"""The ``preview`` stage of ``fabflow build``: ``OUT/preview.html``."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fabflow.build.runner import BuildContext


def stage_preview(ctx: BuildContext) -> None:
    """Export the construction sequence as ``preview.html`` (one offline HTML file).

    Reads ``ctx.results["elements"]``, ``["plan"]`` and, when present,
    ``["localization"]`` (``{visit index: (BasePose, ...)}``); sets
    ``ctx.results["preview"]`` (:class:`~fabflow.preview.export.ExportResult`).
    """
    from fabflow.preview.export import export_html
    from fabflow.preview.inputs import model_for_project

    localization = {int(i): value[0] for i, value in ctx.results.get("localization", {}).items()}
    model = model_for_project(
        ctx.project, ctx.results["elements"], ctx.results["plan"], localization=localization
    )
    result = export_html(model, ctx.out / "preview.html", ctx.project)
    ctx.results["preview"] = result
    ctx.add("preview", "file", f"preview.html ({result.size_bytes / 1e6:.1f} MB)")
    ctx.add("preview", "steps", f"{result.n_steps} (plays {result.duration_s:.0f} s)")
