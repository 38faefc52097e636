"""The ``program`` stage of ``fabflow build``: one robot program per work package."""

from __future__ import annotations

from fabflow.build.context import BuildContext
from fabflow.design.elements import hand_built_stages
from fabflow.localize.plan import VisitPoses, failed_visits
from fabflow.programs.compile import write_programs


def stage_program(ctx: BuildContext) -> None:
    """Build stage: one program per work package in the project's format, under ``programs/``.

    Needs the plan, the elements and the localization; sets ``ctx.programs``.
    """
    project = ctx.project
    localized = ctx.need_localization()
    base_poses = {i: pose for i, (pose, _) in localized.items() if i not in failed(localized)}
    programs, files = write_programs(ctx.need_plan(), ctx.need_elements(), project, base_poses)
    folder = ctx.out / "programs"
    folder.mkdir()
    for name, text in files.items():
        (folder / name).write_text(text, encoding="utf-8")
    ctx.programs = programs
    ctx.add("program", "format", project.program.format)
    ctx.add("program", "programs / files", f"{len(programs)} / {len(files)}")
    ctx.add("program", "motions", sum(len(p.moves) for p in programs))
    ctx.add("program", "robot time (planned)", f"{sum(p.duration for p in programs) / 60:.1f} min")
    checks = [p.checks for p in programs if p.checks]
    if checks:
        changes = [c["configuration_changes"] for c in checks]
        ctx.add(
            "program",
            "configuration changes",
            f"{sum(changes)} (at most {max(changes)} in one program)",
        )
        swings = sum(c["needless_swings"] for c in checks)
        ctx.add("program", "PTP moves swinging A1-A3 widely", swings)
        inside = [p.name for p in programs if p.checks.get("changes_inside_lin")]
        ctx.add(
            "program",
            "configuration changes inside linear moves",
            f"{sum(p.checks['changes_inside_lin'] for p in programs if p.checks)}"
            + (
                f" (in {', '.join(inside[:6])}{', ...' if len(inside) > 6 else ''}: "
                "a controller refuses these; change the station or lift)"
                if inside
                else ""
            ),
        )
        ctx.add(
            "program",
            "linear moves with the wrist interpolated",
            sum(c.get("wrist_interpolated", 0) for c in checks),
        )
        ctx.add(
            "program",
            "linear moves made joint moves at the wrist singularity",
            sum(c.get("joint_through_wrist", 0) for c in checks),
        )
        if any("collision_moves" in c for c in checks):
            colliding = [p.name for p in programs if p.checks.get("collision_moves")]
            ctx.add(
                "program",
                "moves still colliding after re-planning",
                f"{sum(c.get('collision_moves', 0) for c in checks)}"
                + (
                    f" (in {', '.join(colliding[:6])}{', ...' if len(colliding) > 6 else ''}: "
                    "see their headers; do not run them as they are)"
                    if colliding
                    else ""
                ),
            )
    elements = ctx.need_elements()
    plan = ctx.need_plan()
    order = [e for wp in plan.work_packages for e in wp.elements]
    stages = hand_built_stages(elements, order)
    later = sum(k > 0 for k in stages.values())
    if later:
        ctx.add(
            "program",
            "pre-built elements set by hand as the robot goes",
            f"{later} of {len(stages)}: each once what it rests on stands "
            "(program headers: 'hand work'); the collision check assumes so",
        )
    skipped = sorted(failed(localized))
    if skipped:
        visits = ", ".join(str(i + 1) for i in skipped)
        ctx.add("program", "no program (localization failed)", f"visits {visits}")


def failed(localized: VisitPoses) -> set[int]:
    """Work packages whose base pose failed its integrity tests."""
    return {i for i, _ in failed_visits(localized)}
