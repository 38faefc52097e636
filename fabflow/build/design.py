"""The ``design`` stage of ``fabflow build``: elements, ``elements.json``, site plan."""

from __future__ import annotations

from collections import Counter
from functools import partial
from typing import Any

import numpy as np

from fabflow.build.context import BuildContext
from fabflow.design.elements import Element, elements_to_json
from fabflow.design.generate import generate_elements
from fabflow.design.site_plan import write_site_plan
from fabflow.localize.site import site_sensors
from fabflow.output import write_json


def _runs(counts: np.ndarray) -> str:
    """Counts per layer as runs: ``"25 (0-7), 21 (8-17), ..."``."""
    edges = np.flatnonzero(np.diff(counts)) + 1
    starts = np.concatenate(([0], edges))
    ends = np.concatenate((edges, [len(counts)])) - 1
    return ", ".join(
        f"{counts[a]} ({a})" if a == b else f"{counts[a]} ({a}-{b})"
        for a, b in zip(starts, ends, strict=True)
    )


def design_summary(elements: list[Element]) -> list[tuple[str, Any]]:
    """Summary rows: counts per type and part, layers, print path lengths."""
    rows: list[tuple[str, Any]] = []
    types = Counter(e.type for e in elements)
    blocks = [e for e in elements if e.type == "block"]
    if blocks:
        parts = Counter(e.part for e in blocks)
        robot = sum(e.robot_built for e in blocks)
        robot_layers = {e.layer for e in blocks if e.robot_built}
        rows.append(("blocks", f"{len(blocks)} ({robot} robot-built)"))
        rows.append(("blocks per part", ", ".join(f"{p} {n}" for p, n in sorted(parts.items()))))
        per_layer = np.bincount([e.layer for e in blocks])
        rows.append(("blocks per layer", _runs(per_layer)))
        rows.append(
            (
                "block layers",
                f"{max(e.layer for e in blocks) + 1} ({len(robot_layers)} with robot-built blocks)",
            )
        )
    paths = [e for e in elements if e.type == "print_path"]
    if paths:
        length = sum(float(e.attributes.get("length", 0.0)) for e in paths)
        rows.append(("print path layers", len(paths)))
        rows.append(("print path length", f"{length:.2f} m"))
        t = sum(
            float(e.attributes.get("length", 0.0)) / float(e.attributes["speed"]) for e in paths
        )
        rows.append(("print time", f"{t / 60:.1f} min"))
    if types.get("task_point"):
        rows.append(("task points", types["task_point"]))
    return rows


def stage_design(ctx: BuildContext) -> None:
    """Generate the elements; write ``elements.json``, and draw the site plan.

    Sets ``ctx.elements`` (world frame) and ``ctx.site_plan``.
    """
    elements = generate_elements(ctx.project.elements, ctx.project.path, ctx.project.limits)
    ctx.elements = elements
    write_json(
        ctx.out / "elements.json",
        {
            "frame": "world",
            "units": "m",
            "count": len(elements),
            "elements": elements_to_json(elements),
        },
    )
    anchors, instrument = site_sensors(ctx.project)
    ctx.site_plan = partial(
        write_site_plan, elements=elements, anchors=anchors, instrument=instrument
    )
    for item, value in design_summary(elements):
        ctx.add("design", item, value)
