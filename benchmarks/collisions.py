"""Collisions of every robot program of the examples, by the planner's check and by an
independent replay of the JSON command streams.

Plans and localizes each example (no sensor noise), compiles every work package
with the collision re-planning of ``fabflow.programs.replan`` (reporting what
remains instead of failing), then replays each program's JSON command stream
through ``tests/collision_replay.py`` (its own kinematics and geometry) against
the structure as built, at the project's clearance. Prints, per program, the
moves, the JSON setpoints, the moves the planner's check still finds closer than
the clearance, the replay's contacts and the deepest penetration, and the time
of the check.

    python benchmarks/collisions.py [--quick] [--project cabin|print_path]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from _exact import exact_plan  # noqa: E402
from collision_replay import replay  # noqa: E402

from fabflow.design.elements import structure_timeline  # noqa: E402
from fabflow.design.generate import generate_elements  # noqa: E402
from fabflow.programs.compile import program_name  # noqa: E402
from fabflow.programs.replan import replanned_program  # noqa: E402
from fabflow.programs.writers.json_stream import write_json_stream  # noqa: E402
from fabflow.project import load_project  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the cabin's first two programs")
    parser.add_argument("--project", choices=["cabin", "print_path"], action="append")
    args = parser.parse_args()
    names = args.project or ["cabin", "print_path"]
    if args.quick:
        names = ["cabin"]
    print(
        f"{'project':<11} {'program':<12} {'moves':>6} {'setpoints':>9} {'check s':>8} "
        f"{'check moves':>11} {'replay contacts':>15} {'replay moves':>12} {'deepest mm':>10}"
    )
    for name in names:
        project = load_project(ROOT / "projects" / name)
        elements = generate_elements(project.elements, project.path)
        project, elements, plan, located = exact_plan(project, elements)
        by_id = {e.id: e for e in elements}
        timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
        packages = [
            (wp, built, coming)
            for wp, (built, coming) in zip(plan.work_packages, timeline, strict=True)
            if wp.elements and wp.index in located
        ]
        totals = np.zeros(5)
        for wp, built, coming in packages[: 2 if args.quick else None]:
            package = [by_id[e] for e in wp.elements]
            T_world_base = np.asarray(located[wp.index].T_world_base, dtype=float)
            start = time.perf_counter()
            program, contacts = replanned_program(
                program_name(wp), package, built, project, T_world_base, {}, coming=coming
            )
            seconds = time.perf_counter() - start
            stream = next(iter(write_json_stream(program).values()))
            robot = [e.id for e in built if e.robot_built]  # the replay adds the hand-built
            found = replay(stream, elements, robot, project.program.clearance)
            setpoints = stream.count('"setpoint"')
            check_moves = len({c.move for c in contacts})
            replay_moves = len({(c[0], c[1]) for c in found})
            deepest = -1000 * min((c[4] for c in found), default=0.0)
            totals += [len(program.moves), setpoints, check_moves, len(found), replay_moves]
            print(
                f"{name:<11} {program.name:<12} {len(program.moves):>6} {setpoints:>9} "
                f"{seconds:>8.2f} {check_moves:>11} {len(found):>15} {replay_moves:>12} "
                f"{max(deepest, 0.0):>10.1f}",
                flush=True,
            )
        moves, setpoints, check_moves, n_found, replay_moves = totals.astype(int)
        print(
            f"{name:<11} {'all':<12} {moves:>6} {setpoints:>9} {'':>8} {check_moves:>11} "
            f"{n_found:>15} {replay_moves:>12}"
        )


if __name__ == "__main__":
    main()
