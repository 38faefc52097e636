"""Configuration continuity of the programs fabflow writes: swings and configuration changes.

Plans and localizes the example projects (exact localization, so the figures
do not depend on the sensor noise), writes every program, and prints per
program the moves, PTP moves, needless swings (A2 or A3 turning more than
90 deg, or A1 turning 30 deg more than the wrist centre's azimuth), the
configuration changes between targets and inside linear moves, and how many
PTP targets that repeat an earlier pose of the same program got another
configuration, or other joint values (identical targets should get the same).

    python benchmarks/configurations.py [--project cabin] [--quiet] [--quick]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _exact import exact_plan

from fabflow.design.generate import generate_elements
from fabflow.programs.compile import write_programs
from fabflow.programs.motion_checks import configuration_of
from fabflow.project import load_project
from fabflow.robots.catalog import get_robot

ROOT = Path(__file__).resolve().parents[1]


def repeated_target_mismatches(
    poses: np.ndarray, q: np.ndarray, config: np.ndarray
) -> tuple[int, int, int]:
    """PTP targets repeating an earlier pose (to 0.1 mm, 1e-4), how many of them got
    another configuration (branch), and how many other joint values (a turn of A1
    or the wrist, a different Turn T on a KUKA)."""
    key = np.round(poses.reshape(len(poses), -1), 4)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    repeats = np.flatnonzero(first[inverse] != np.arange(len(poses)))
    origin = first[inverse[repeats]]
    other_config = config[repeats] != config[origin]
    differ = np.abs(q[repeats] - q[origin]).max(axis=1) > 1e-6
    return len(repeats), int(other_config.sum()), int(differ.sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--project", default="cabin", help="example project folder name")
    parser.add_argument("--quiet", action="store_true", help="totals only")
    parser.add_argument("--quick", action="store_true", help="the same (one project, fast)")
    args = parser.parse_args()
    project = load_project(ROOT / "projects" / args.project)
    elements = generate_elements(project.elements, project.path)
    project, elements, plan, poses = exact_plan(project, elements)
    programs, _ = write_programs(plan, elements, project, poses, fmt="json")
    robot = get_robot(project.robot.model)
    header = (
        f"{'program':<14} {'moves':>6} {'ptp':>5} {'swings':>7} {'changes':>8} "
        f"{'in lin':>7} {'repeats':>8} {'other S':>8} {'other q':>8}"
    )
    if not args.quiet:
        print(header)
    total = np.zeros(8, dtype=int)
    worst_changes = 0
    avoidable = 0
    for program in programs:
        moves = program.moves
        q = np.stack([m.q for m in moves])
        checks = program.checks
        ptp = np.array([m.kind == "ptp" and not m.joint for m in moves])
        T = np.stack([m.T_world_tool for m in moves])[ptp]
        config = configuration_of(robot, q[ptp])
        repeats, other_config, differ = repeated_target_mismatches(T, q[ptp], config)
        row = [
            checks["moves"],
            checks["ptp_moves"],
            checks["needless_swings"],
            checks["configuration_changes"],
            checks["changes_inside_lin"],
            repeats,
            other_config,
            differ,
        ]
        total += row
        worst_changes = max(worst_changes, checks["configuration_changes"])
        avoidable += checks["avoidable_swings"]
        if not args.quiet:
            widths = (6, 5, 7, 8, 7, 8, 8, 8)
            cells = " ".join(f"{v:>{w}}" for v, w in zip(row, widths, strict=True))
            print(f"{program.name:<14} {cells}")
    print(
        f"{args.project}: {len(programs)} programs, {total[0]} moves, {total[1]} PTP, "
        f"{total[2]} wide swings ({avoidable} avoidable), {total[3]} configuration changes "
        f"(at most {worst_changes} in one program), {total[4]} inside linear moves; "
        f"of {total[5]} repeated PTP targets "
        f"{total[6]} in another configuration, {total[7]} with other joint values"
    )


if __name__ == "__main__":
    main()
