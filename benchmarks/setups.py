"""Localization layouts planned for whole builds: total station set-ups and UWB anchors.

For the cabin and the village (nine cabins), plans the project and then, per
localization variant, checks or plans what stands on the site: the total
station's set-ups (procedures ``three_point`` and ``arbitrary``, registered on
control points or on the robot's prisms) and the UWB anchors (the project's,
checked, and planned without them). Prints per row the set-ups or anchors, the
largest predicted XY sigma over the work packages, and the planning time (median
of ``--repeats``, the plan itself not timed).

    python benchmarks/setups.py [--quick] [--repeats N]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from fabflow.design.generate import generate_elements
from fabflow.errors import LocalizationError
from fabflow.localize.anchors import layout_anchors
from fabflow.localize.setups import plan_setups
from fabflow.project import Project, TotalStationSetup, load_project
from fabflow.tasks.planner import plan_project

ROOT = Path(__file__).resolve().parents[1]


def _with(project: Project, **fields: object) -> Project:
    loc = project.localization.model_copy(update=fields)
    return project.model_copy(update={"localization": loc})


def _variants(project: Project) -> list[tuple[str, Project]]:
    ts = project.localization.total_station or TotalStationSetup()
    out = []
    for procedure in ("three_point", "arbitrary"):
        for stationing in ("control_points", "robot_points"):
            setup = ts.model_copy(update={"procedure": procedure, "stationing": stationing})
            name = f"total station, {procedure}, {stationing.replace('_', ' ')}"
            out.append((name, _with(project, method="total_station", total_station=setup)))
    uwb = project.localization.uwb
    if uwb is not None and uwb.anchors:
        out.append(("UWB, the project's anchors", _with(project, method="uwb")))
    if uwb is not None:
        planned = uwb.model_copy(update={"anchors": {}})
        out.append(("UWB, anchors planned", _with(project, method="uwb", uwb=planned)))
    return out


def _row(project: Project, plan, elements) -> str:  # type: ignore[no-untyped-def]
    if project.localization.method == "uwb":
        _, coverage = layout_anchors(project, plan, elements)
        sigma = coverage.judged
        nlos = int(coverage.through_structure.sum())
        return (
            f"{len(coverage.anchor_ids)} anchors, sigma max {1e3 * sigma.max():.0f} mm "
            f"(target {1e3 * coverage.target:.0f}), {nlos} packages only through walls"
        )
    setups = plan_setups(project, plan, elements)
    moves = ", ".join(f"{s.id} {s.packages[0] + 1}-{s.packages[-1] + 1}" for s in setups)
    sigma = max(s.predicted_sigma for s in setups)
    return f"{len(setups)} set-ups ({moves}), sigma max {1e3 * sigma:.1f} mm"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the cabin only, one repeat")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    repeats = 1 if args.quick else args.repeats
    names = ["cabin"] if args.quick else ["cabin", "village"]
    print(f"{'project':<8} {'variant':<46} {'median s':>9}  result")
    for name in names:
        base = load_project(ROOT / "projects" / name)
        elements = generate_elements(base.elements, base.path)
        plan = plan_project(base, elements)
        for label, project in _variants(base):
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                try:
                    result = _row(project, plan, elements)
                except LocalizationError as exc:
                    result = f"error: {str(exc)[:110]}"
                times.append(time.perf_counter() - start)
            print(f"{name:<8} {label:<46} {statistics.median(times):>9.2f}  {result}")
    np.set_printoptions()


if __name__ == "__main__":
    main()
