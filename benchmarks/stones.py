"""Stones (paper 002): registration, grasp success and placement over simulated runs.

Runs the stone wall study of ``projects/stone_wall`` (each run a new seeded
stockpile, new sensor noise) and prints its figures beside the paper's:
registration success (ICP RMSE below 3 cm and every stone one object) and its
median time, the success of the best-ranked reachable grasp, and the
placement error of the stones set in the wall. The paper's times come from an
Intel Xeon E-2176M; here the runs share a 2-worker local Dask cluster, so the
registration time is that of one core with another run beside it.

    python benchmarks/stones.py [--quick] [--runs N] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from fabflow.project import load_project
from fabflow.sim.monte_carlo import dask_client
from fabflow.sim.stones import PAPER, simulate_stones, stone_table_rows

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 runs (a smoke test)")
    parser.add_argument("--runs", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="write the summary here")
    args = parser.parse_args()
    runs = 2 if args.quick else args.runs
    project = load_project(ROOT / "projects" / "stone_wall")
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder, dask_client(n_workers=2) as client:
        summary = simulate_stones(project, Path(folder), runs, args.seed, client=client)
    elapsed = time.perf_counter() - start
    s = summary["stones"]
    print(f"stone wall, {runs} runs ({elapsed:.0f} s, {elapsed / runs:.1f} s per run)")
    print(f"{'figure':<34} {'fabflow':>22} {'paper 002':>14}")
    for name, ours, paper in stone_table_rows(summary):
        print(f"{name:<34} {ours:>22} {paper:>14}")
    ratio = s["grasp_success"] / PAPER["grasp_success"]
    print(f"{'grasp success / paper':<34} {ratio:>22.2f} {'>= 1':>14}")
    if args.json is not None:
        args.json.write_text(json.dumps(summary, indent=2), encoding="utf-8")


if __name__ == "__main__":
    main()
