"""The ``plan`` stage of ``fabflow build`` and the files ``fabflow plan`` writes."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from fabflow.build.context import BuildContext
from fabflow.design.elements import Element
from fabflow.design.site_plan import write_site_plan
from fabflow.localize.setups import (
    InstrumentSetup,
    control_points,
    planned_setups,
    setup_rows,
    setups_document,
)
from fabflow.localize.site import site_sensors
from fabflow.output import write_json
from fabflow.project import Project
from fabflow.tasks.plan import Plan
from fabflow.tasks.planner import make_plan
from fabflow.tasks.split import with_pieces
from fabflow.version import __version__


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
    out: Path,
    project: Project,
    elements: Sequence[Element],
    plan: Plan,
    setups: Sequence[InstrumentSetup] | None = None,
) -> None:
    """Write ``plan.json`` and redraw ``site_plan.dxf`` with the stations into ``out``;
    with total station ``setups``, ``instrument_setups.json`` too, and the set-ups and
    control points on the site plan."""
    write_json(
        out / "plan.json",
        {"fabflow_version": __version__, "frame": "world", "units": "m", **plan.to_dict()},
    )
    anchors, instrument = site_sensors(project)
    controls = None
    if setups is not None:
        write_json(out / "instrument_setups.json", setups_document(project, setups))
        instrument = {s.id: s.T_world_instrument for s in setups}
        controls = control_points(project)
    write_site_plan(
        out / "site_plan.dxf",
        with_pieces(elements, plan.split_elements),
        stations=plan.stations,
        platform_footprint=tuple(project.robot.platform.footprint),
        anchors=anchors,
        instrument=instrument,
        control_points=controls,
    )


def stage_plan(ctx: BuildContext) -> None:
    """Slice the elements into work packages; write ``plan.json``, redraw the site plan.

    Reads the elements; sets ``ctx.plan`` and, for the total station, ``ctx.setups``
    (``instrument_setups.json``). When print paths were split into
    per-station pieces, ``ctx.elements`` is replaced by the list with the pieces
    (see :mod:`fabflow.tasks.split`).
    """
    plan = make_plan(ctx.project, ctx.need_elements())
    ctx.plan = plan
    elements = with_pieces(ctx.need_elements(), plan.split_elements)
    ctx.elements = elements
    ctx.setups = planned_setups(ctx.project, plan, elements)
    write_plan_outputs(ctx.out, ctx.project, elements, plan, ctx.setups)
    for item, value in plan_rows(plan):
        ctx.add("plan", item, value)
    for item, value in setup_rows(ctx.setups or ()):
        ctx.add("plan", item, value)
