"""Station planning time for the cabin and for larger synthetic projects (rows of cabins).

Run ``.venv/bin/python benchmarks/plan.py`` (cabin, 10x, 100x) or with ``--quick``
(cabin and 2x, under ~20 s). Prints the median planning wall and CPU time per
size (CPU time is steadier on a shared machine; the growth uses it), the
stations, visits and travel, the time per planning step, and how time grows
with the element count: the exponent ``b`` of ``time ~ n^b`` between
consecutive sizes (``b = 1`` is linear; ``n log n`` shows as slightly above 1).
The reach model is computed (or loaded from its disk cache) before timing.
"""

from __future__ import annotations

import argparse
import itertools
import math
import statistics
import time
from pathlib import Path

from fabflow.project import load_project
from fabflow.robots.reach_model import reach_model
from fabflow.tasks.planner import plan_project
from fabflow.tasks.synthetic import cabin_rows

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes only (CI smoke run)")
    args = parser.parse_args()
    sizes = [(1, 3), (2, 1)] if args.quick else [(1, 5), (10, 3), (100, 1)]

    base = load_project(ROOT / "projects" / "cabin" / "project.yaml")
    t0 = time.perf_counter()
    reach_model(base.robot.model, base.robot.tool.T_flange_tool.matrix())
    print(f"reach model ready in {time.perf_counter() - t0:.2f} s (cached afterwards)\n")

    header = (
        f"{'cabins':>6} {'elements':>8} {'robot':>7} {'median s':>9} {'cpu s':>8} {'stations':>8} "
        f"{'bound':>5} {'visits':>6} {'travel m':>9}  {'cand':>5} {'cover':>5} {'select':>6} "
        f"{'awkward':>7} {'order':>5} {'pack':>5}  selection"
    )
    print(header)
    print("-" * len(header))
    rows = []
    for n_cabins, repeats in sizes:
        project, elements = cabin_rows(base, n_cabins)
        times = []
        cpu = []
        plan = None
        for _ in range(repeats):
            t = time.perf_counter()
            c = time.process_time()
            plan = plan_project(project, elements)
            times.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
        assert plan is not None
        s = plan.summary
        ts = s["time_s"]
        med = statistics.median(times)
        med_cpu = statistics.median(cpu)
        n_robot = s["elements"]
        rows.append((n_robot, med_cpu))
        print(
            f"{n_cabins:>6} {len(elements):>8} {n_robot:>7} {med:>9.2f} {med_cpu:>8.2f} "
            f"{s['stations']:>8} "
            f"{s['station_lower_bound']:>5} {s['visits']:>6} {s['travel_m']:>9.1f}  "
            f"{ts['candidates']:>5.2f} {ts['coverage']:>5.2f} {ts['selection']:>6.2f} "
            f"{ts['awkward_lifts']:>7.2f} {ts['order']:>5.2f} {ts['packages']:>5.2f}  "
            f"{s['selection']}",
            flush=True,
        )
    print("\ngrowth of planning CPU time with the robot-built element count:")
    for (n0, t0_), (n1, t1) in itertools.pairwise(rows):
        b = math.log(t1 / t0_) / math.log(n1 / n0)
        nlogn = (n1 * math.log(n1)) / (n0 * math.log(n0))
        print(
            f"  {n0:>6} -> {n1:>6} elements: x{n1 / n0:.1f} elements, x{t1 / t0_:.1f} time "
            f"(n log n would be x{nlogn:.1f}), exponent b = {b:.2f}"
        )


if __name__ == "__main__":
    main()
