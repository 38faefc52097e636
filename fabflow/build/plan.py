"""The ``plan`` stage of ``fabflow build`` and the files ``fabflow plan`` writes."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path

from fabflow.build.context import BuildContext
from fabflow.design.elements import Element
from fabflow.design.site_plan import write_site_plan
from fabflow.localize.layout import SiteLayout, site_layout
from fabflow.localize.setups import control_points
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
    layout: SiteLayout | None = None,
    draw: bool = True,
) -> Callable[[Path], Path]:
    """Write ``plan.json`` and redraw ``site_plan.dxf`` with the stations into ``out``;
    with the localization's ``layout``, its files too (``instrument_setups.json``,
    ``uwb_anchors.json``) and its set-ups, control points and anchors on the site plan.

    Returns the site plan's drawing (it takes the file's path); ``draw=False``
    leaves drawing it to the caller.
    """
    write_json(
        out / "plan.json",
        {"fabflow_version": __version__, "frame": "world", "units": "m", **plan.to_dict()},
    )
    if layout is not None:
        project = layout.project
        layout.write(out, plan)
    anchors, instrument = site_sensors(project)
    controls = None
    if layout is not None and layout.setups is not None:
        instrument = {s.id: s.T_world_instrument for s in layout.setups}
        controls = control_points(project)
    drawing = partial(
        write_site_plan,
        elements=with_pieces(elements, plan.split_elements),
        stations=plan.stations,
        platform_footprint=tuple(project.robot.platform.footprint),
        anchors=anchors,
        instrument=instrument,
        control_points=controls,
    )
    if draw:
        drawing(out / "site_plan.dxf")
    return drawing


def stage_plan(ctx: BuildContext) -> None:
    """Slice the elements into work packages; write ``plan.json``; the site plan is
    redrawn with the stations (``ctx.site_plan``).

    Reads the elements; sets ``ctx.plan``, and the localization's layout
    (:func:`~fabflow.localize.layout.site_layout`): ``ctx.setups`` for the total
    station, ``ctx.project`` with its planned UWB anchors. When print paths were split into
    per-station pieces, ``ctx.elements`` is replaced by the list with the pieces
    (see :mod:`fabflow.tasks.split`).
    """
    plan = make_plan(ctx.project, ctx.need_elements())
    ctx.plan = plan
    elements = with_pieces(ctx.need_elements(), plan.split_elements)
    ctx.elements = elements
    layout = site_layout(ctx.project, plan, elements)
    ctx.project = layout.project
    ctx.setups = layout.setups
    ctx.site_plan = write_plan_outputs(ctx.out, ctx.project, elements, plan, layout, draw=False)
    for item, value in plan_rows(plan) + layout.rows(plan):
        ctx.add("plan", item, value)
