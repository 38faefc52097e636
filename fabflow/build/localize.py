"""The ``localize`` stage of ``fabflow build``: a base pose for every visit of the plan."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from fabflow.build.context import BuildContext
from fabflow.localize.plan import VisitPoses, enforce_integrity, localize_plan
from fabflow.output import write_json
from fabflow.transforms.se3 import pose_error


def stage_localize(ctx: BuildContext) -> None:
    """Build stage: localize every visit of the plan; writes ``localization/visit_NN_S.json``.

    One file per work package (``NN`` its 1-based index, ``S`` its station);
    packages that continue a visit after a lift move carry the visit's
    measurement moved by the lift (``quality.measured_in_package``).

    Needs the plan and the elements; sets ``ctx.localization``.
    """
    project = ctx.project
    plan = ctx.need_plan()
    rng = np.random.default_rng(project.simulation.seed)
    results = localize_plan(project, plan, ctx.need_elements(), rng, setups=ctx.setups)
    warnings = enforce_integrity(project, plan, results)
    ctx.localization = results
    folder = ctx.out / "localization"
    folder.mkdir()
    errors, sigma = [], []
    for wp in plan.work_packages:
        estimate, T_true = results[wp.index]
        error = pose_error(estimate.T_world_base, T_true)
        if "measured_in_package" not in estimate.quality:
            errors.append(np.linalg.norm(error[:2]))
            sigma.append(float(np.sqrt(np.trace(estimate.covariance[:2, :2]))))
        write_json(
            folder / f"visit_{wp.index + 1:02d}_{wp.station.id}.json",
            {
                **estimate.to_dict(),
                "visit": wp.index + 1,
                "simulated": True,
                "T_world_base_true": T_true,
                "error": {"xyz_m": error[:3], "rotation_rad": error[3:]},
            },
        )
    ctx.add("localize", "method", project.localization.method)
    ctx.add("localize", "visits localized", len(errors))
    if errors:  # a plan without robot-built elements has no visits
        ctx.add(
            "localize",
            "XY error, simulated (mean / max)",
            f"{1000 * np.mean(errors):.1f} / {1000 * np.max(errors):.1f} mm",
        )
        ctx.add("localize", "XY sigma, predicted (mean)", f"{1000 * np.mean(sigma):.1f} mm")
    for item, value in integrity_rows(results):
        ctx.add("localize", item, value)
    for message in warnings:
        ctx.add("localize", "warning", message)


def integrity_rows(results: VisitPoses) -> list[tuple[str, str]]:
    """Summary rows: visits by integrity status, degraded ones, the largest protection level."""
    visits = [est for est, _ in results.values() if "measured_in_package" not in est.quality]
    tested = [e.integrity for e in visits if e.integrity is not None]
    status = Counter("untested" if e.integrity is None else e.integrity.status for e in visits)
    rows = [("integrity", ", ".join(f"{n} {s}" for s, n in sorted(status.items())))]
    degraded = sum(1 for i in tested if i.checks.get("degraded"))
    if degraded:
        rows.append(
            (
                "integrity degraded",
                f"{degraded} of {len(visits)} visits: protection level above the alert limit",
            )
        )
    levels = [i.protection_level.get("horizontal", 0.0) for i in tested if i.protection_level]
    if levels:
        worst = max(math.inf if v is None else float(v) for v in levels)
        shown = f"{1000 * worst:.1f} mm" if math.isfinite(worst) else "unbounded"
        rows.append(("protection level XY (max)", shown))
    return rows
