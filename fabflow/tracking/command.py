"""What ``fabflow track`` does: print a project's path closed and open loop, write the results."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console
from rich.table import Table

from fabflow.output import atomic_output_dir
from fabflow.project import load_project
from fabflow.tracking.report import write_outputs
from fabflow.tracking.run import track_print


def run_track(project_path: Path, out: Path, seed: int | None, console: Console) -> None:
    """Run the closed-loop and the open-loop print of a project and write OUT.

    Parameters
    ----------
    project_path
        Project YAML file or folder (a print path from one station, an excavator).
    out
        Output folder (written atomically: complete or not at all).
    seed
        Seed of the machine's errors and noise (default: ``simulation.seed``).
    console
        Where the progress and the table go.
    """
    p = load_project(project_path).without_stone_wall("track")
    seed = p.simulation.seed if seed is None else seed
    with atomic_output_dir(out) as staging:
        with console.status("printing closed loop (LiDAR ICP + kinematics EKF)"):
            closed = track_print(p, "closed", seed)
        with console.status("printing open loop (joint sensors only)"):
            open_ = track_print(p, "open", seed)
        meta = {
            "project": p.name,
            "seed": seed,
            "robot": p.robot.name,
            "icp_latency_s": p.tracking.icp_latency_s,
            "settle_s": p.tracking.settle_s,
            "samples": len(closed.t),
        }
        s = write_outputs(closed, open_, staging, meta)
    table = Table(title=f"fabflow track: {p.name} (seed {seed})")
    for name in ("figure", "RMSE cm", "max cm", "paper 000"):
        table.add_column(name, justify="left" if name == "figure" else "right")
    paper = {k: f"{100 * v:.2f}" for k, v in s["paper"].items()}
    est = s["estimation"]
    rows = (
        (
            "tracking, closed loop",
            s["tracking"]["closed_loop"],
            f"{paper['tracking_rmse_m']} / {paper['tracking_max_m']}",
        ),
        ("tracking, open loop", s["tracking"]["open_loop"], ""),
        ("estimate: fused (100 Hz)", est["fused"], ""),
        ("estimate: kinematics alone", est["kinematics"], paper["kinematics_rmse_m"]),
        ("estimate: last ICP fix (held)", est["icp"], ""),
        ("ICP fix at its scan time", est["icp_at_scan"], paper["icp_rmse_m"]),
    )
    for name, v, ref in rows:
        table.add_row(name, f"{100 * v['rmse_m']:.2f}", f"{100 * v['max_m']:.2f}", ref)
    console.print(table)
    icp, speed = s["icp"], s["speed"]
    console.print(
        f"closed loop {s['tracking']['improvement']:.1f}x better than open loop; ICP fixes "
        f"{icp['applied']} applied, {icp['gated']} gated, {icp['failed']} failed; "
        f"{speed['simulated_s']:.0f} s of machine time simulated "
        f"{speed['realtime_factor']:.1f}x faster than real time"
    )
    console.print(f"[green]wrote[/] {Path(out).resolve()}")
