"""The ``plan`` stage of ``fabflow build`` and the files ``fabflow plan`` writes."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from fabflow import __version__
from fabflow.design.elements import Element
from fabflow.output import write_json
from fabflow.project import Project
from fabflow.tasks.plan import Plan
from fabflow.tasks.planner import plan_project
from fabflow.tasks.split import with_pieces
from fabflow.tasks.verify import unreachable_targets

if TYPE_CHECKING:
    from fabflow.build.runner import BuildContext


def plan_rows(plan: Plan) -> list[tuple[str, str]]:
    """Summary rows ``(item, value)``: stations, elements per station, visits, travel."""
    s = plan.summary
    rows = [
        ("stations", f"{s.get('stations', 0)} (lower bound {s.get('station_lower_bound', 0)})"),
        (
            "elements per station",
            ", ".join(f"{k} {v}" for k, v in s.get("elements_per_station", {}).items()) or "-",
        ),
        ("visits", f"{s.get('visits', 0)} ({s.get('work_packages', 0)} work packages)"),
        ("travel", f"{s.get('travel_m', 0.0):.2f} m"),
    ]
    if "ik_unreachable" in s:
        bad = s["ik_unreachable"]
        rows.append(("targets checked by IK", f"{s.get('elements', 0) - len(bad)} reachable"))
    if "time_s" in s:
        rows.append(("planning time", f"{s['time_s']['total']:.2f} s"))
    rows += [("note", n) for n in plan.notes]
    return rows


def write_plan_outputs(
    out: Path, project: Project, elements: Sequence[Element], plan: Plan
) -> None:
    """Write ``plan.json`` and redraw ``site_plan.dxf`` with the stations into ``out``."""
    from fabflow.build.design import site_sensors
    from fabflow.design.site_plan import write_site_plan

    write_json(
        out / "plan.json",
        {"fabflow_version": __version__, "frame": "world", "units": "m", **plan.to_dict()},
    )
    anchors, instrument = site_sensors(project)
    write_site_plan(
        out / "site_plan.dxf",
        with_pieces(elements, plan.split_elements),
        stations=plan.stations,
        platform_footprint=tuple(project.robot.platform.footprint),
        anchors=anchors,
        instrument=instrument,
    )


def make_plan(project: Project, elements: Sequence[Element]) -> Plan:
    """Plan the project and record the inverse-kinematics check of every target."""
    plan = plan_project(project, elements)
    bad = unreachable_targets(plan, project)
    if bad is None:
        return plan
    notes = plan.notes
    if bad:
        notes = (
            *notes,
            f"{len(bad)} target(s) fail the inverse-kinematics check: {', '.join(bad[:12])}",
        )
    return dataclasses.replace(plan, notes=notes, summary={**plan.summary, "ik_unreachable": bad})


def stage_plan(ctx: BuildContext) -> None:
    """Slice the elements into work packages; write ``plan.json``, redraw the site plan.

    Reads ``ctx.results["elements"]``; sets ``ctx.results["plan"]`` (:class:`Plan`). When
    print paths were split into per-station pieces, ``ctx.results["elements"]`` is
    replaced by the list with the pieces (see :mod:`fabflow.tasks.split`).
    """
    plan = make_plan(ctx.project, ctx.results["elements"])
    ctx.results["plan"] = plan
    elements = with_pieces(ctx.results["elements"], plan.split_elements)
    ctx.results["elements"] = elements
    write_plan_outputs(ctx.out, ctx.project, elements, plan)
    for item, value in plan_rows(plan):
        ctx.add("plan", item, value)
