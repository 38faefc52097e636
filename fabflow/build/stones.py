"""The ``stones`` stage of ``fabflow build``: a dry-stone wall from found stones.

Scans the (simulated) stockpile, fills the object database, plans a grasp and
a release for every slot, writes ``objects.json`` (with one PLY per object),
``grasps.json`` and one program per stone under ``programs/``.
"""

from __future__ import annotations

import numpy as np

from fabflow.build.context import BuildContext
from fabflow.preview.stones import export_stone_html
from fabflow.programs.writers import writer_for
from fabflow.stones.outputs import write_grasps, write_objects
from fabflow.stones.programs import pick_program
from fabflow.stones.run import run_stone_wall


def stage_stones(ctx: BuildContext) -> None:
    """Perceive and plan the stone wall: ``objects.json``, ``grasps.json``; sets ``ctx.stones``."""
    run = run_stone_wall(ctx.project)
    ctx.stones = run
    write_objects(ctx.out, run.db)
    write_grasps(ctx.out, run.picks)
    p = run.perception
    reg = p.registration
    ctx.add("stones", "objects found", f"{len(p.db)} (segments of the scanned map)")
    if reg is not None:
        ctx.add(
            "stones",
            "vision map registration",
            f"RMSE {1e3 * reg.rmse:.1f} mm, {reg.n_centroid_matches} segments matched, "
            f"{p.registration_time_s:.2f} s",
        )
    elif p.registration_error is not None:
        ctx.add("stones", "vision map registration", f"rejected: {p.registration_error}")
    filled = [k for k in run.picks if k.T_grasp is not None]
    ctx.add("stones", "slots filled", f"{len(filled)} of {len(run.picks)}")
    for k in run.picks:
        for object_id, why in k.passed_over:
            ctx.add("stones", f"slot {k.slot}", f"passed over object {object_id}: {why}")
        if k.reason:
            ctx.add("stones", f"slot {k.slot}", k.reason)
    held = [k.outcome.success for k in filled if k.outcome is not None]
    if held:
        ctx.add("stones", "grasps held (simulated)", f"{sum(held)} of {len(held)}")
    errors = np.array([k.placement_error for k in filled])
    if len(errors):
        ctx.add(
            "stones",
            "placement error (simulated)",
            f"RMSE {1e3 * np.sqrt(np.mean(errors**2)):.0f} mm, max {1e3 * errors.max():.0f} mm",
        )


def stage_stone_programs(ctx: BuildContext) -> None:
    """One program per stone under ``programs/``; sets ``ctx.programs``."""
    project, run = ctx.project, ctx.need_stones()
    writer = writer_for(project.program.format, project.robot.name)
    folder = ctx.out / "programs"
    folder.mkdir()
    programs = []
    for i, pick in enumerate(run.picks):
        if pick.T_grasp is None:
            continue
        program = pick_program(project, pick, run.db.get(pick.object_id), run.T_world_base, i)
        programs.append(program)
        for name, text in writer.write(program).items():
            (folder / name).write_text(text, encoding="utf-8")
    ctx.programs = programs
    ctx.add("program", "format", project.program.format)
    ctx.add("program", "programs", len(programs))
    ctx.add("program", "robot time (planned)", f"{sum(p.duration for p in programs) / 60:.1f} min")


def stage_stone_preview(ctx: BuildContext) -> None:
    """The stone wall's preview as ``preview.html``; sets ``ctx.preview``."""
    result = export_stone_html(ctx.need_stones(), ctx.out / "preview.html", ctx.project)
    ctx.preview = result
    ctx.add("preview", "file", f"preview.html ({result.size_bytes / 1e6:.1f} MB)")
    ctx.add("preview", "steps", f"{result.n_steps} (plays {result.duration_s:.0f} s)")
