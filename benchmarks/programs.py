"""Time to write every robot program of a project, inverse kinematics checks included.

Plans and localizes once (not timed), then times ``write_programs`` (motions,
IK of every target and every 2 cm step of every linear move, the writer) for
the cabin and for a 10x larger project (ten cabins), in KRL and as a JSON
stream, without the collision check. Prints medians over repeats, and the CPU
time. Target: the cabin in under 1 s. The cabin's ``replan`` row times writing
its KRL programs with the check and the collision re-planning as the project
sets them (``program.check_collisions``), the ``collide`` row the collision
check of all its programs on its own (the IK solves column there counts the
contacts found).

    python benchmarks/programs.py [--quick] [--repeats N]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
from _exact import exact_plan

from fabflow.design.elements import structure_timeline
from fabflow.design.generate import generate_elements
from fabflow.programs.collision import check_package
from fabflow.programs.collision_model import environment
from fabflow.programs.compile import write_programs
from fabflow.project import load_project
from fabflow.tasks.synthetic import cabin_rows

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="cabin only, one repeat")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    repeats = 1 if args.quick else args.repeats

    cabin = load_project(ROOT / "projects" / "cabin")
    cases = [("cabin", cabin, generate_elements(cabin.elements, cabin.path))]
    if not args.quick:
        big, big_elements = cabin_rows(cabin, 10)
        cases.append(("10 cabins", big, big_elements))

    print(
        f"{'project':<10} {'format':<9} {'programs':>8} {'motions':>8} {'IK solves':>10} "
        f"{'median s':>9} {'cpu s':>7} {'per motion us':>14}"
    )
    for label, project, elements in cases:
        project, elements, plan, poses = exact_plan(project, elements)
        checked = project
        project = project.model_copy(
            update={"program": project.program.model_copy(update={"check_collisions": False})}
        )
        rows = [(p, fmt, fmt) for p, fmt in ((project, "krl"), (project, "json"))]
        if label == "cabin" and checked.program.check_collisions:
            rows.append((checked, "krl", "replan"))
        for settings, fmt, name in rows:
            times, cpu = [], []
            for _ in range(repeats):
                start, start_cpu = time.perf_counter(), time.process_time()
                programs, _ = write_programs(plan, elements, settings, poses, fmt)
                times.append(time.perf_counter() - start)
                cpu.append(time.process_time() - start_cpu)
            moves = [m for p in programs for m in p.moves]
            solves = len(moves) + sum(0 if m.via_q is None else len(m.via_q) for m in moves)
            median = statistics.median(times)
            print(
                f"{label:<10} {name:<9} {len(programs):>8} {len(moves):>8} {solves:>10} "
                f"{median:>9.3f} {statistics.median(cpu):>7.3f} "
                f"{1e6 * median / len(moves):>14.1f}"
            )
        if label == "cabin":
            _collision_row(label, project, plan, elements, programs, repeats)


def _collision_row(label, project, plan, elements, programs, repeats) -> None:
    """The collision check of every program alone (obstacles as built before each)."""
    by_id = {e.id: e for e in elements}
    timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
    packages = [(wp, *t) for wp, t in zip(plan.work_packages, timeline, strict=True) if wp.elements]
    jobs = []
    for (wp, built, coming), program in zip(packages, programs, strict=True):
        package = [by_id[e] for e in wp.elements]
        T_world_base = np.linalg.inv(program.T_base_world)
        env = environment(project, T_world_base, built, package, coming)
        jobs.append((program, env, package))
    times, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        contacts = [c for p, env, pkg in jobs for c in check_package(p, project, env, pkg)]
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    moves = sum(len(p.moves) for p in programs)
    median = statistics.median(times)
    print(
        f"{label:<10} {'collide':<9} {len(programs):>8} {moves:>8} {len(contacts):>10} "
        f"{median:>9.3f} {statistics.median(cpu):>7.3f} {1e6 * median / moves:>14.1f}"
    )


if __name__ == "__main__":
    main()
