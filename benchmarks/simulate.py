"""Monte Carlo simulation benchmark: simulated construction runs of the cabin per second.

Prints, for each localization method, the CPU time of one run (median), runs per
second serially (in this process) and on a local Dask cluster of 2 single-threaded
worker processes, and the projected time of 1,000 runs; then (full mode) times
1,000 UWB runs of the cabin on the cluster against the 60 s target. The elements
and the plan are computed once (not timed), as ``fabflow simulate`` does.

Run: ``.venv/bin/python benchmarks/simulate.py [--quick] [--methods uwb,total_station,icp]``.
``--quick`` (CI smoke run) simulates a few UWB runs of the small test project
(``tests/data/sim``: four task points, one station) serially and on 2 workers.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from fabflow.design.generate import generate_elements
from fabflow.errors import FabflowError
from fabflow.project import load_project
from fabflow.sim.monte_carlo import comparison_row, dask_client, run_study, summarize
from fabflow.sim.run import Study, prepare_study, simulate_run
from fabflow.tasks.planner import plan_project

ROOT = Path(__file__).resolve().parents[1]
CABIN = ROOT / "projects" / "cabin" / "project.yaml"
SMALL = ROOT / "tests" / "data" / "sim" / "project.yaml"
TARGET_RUNS, TARGET_S = 1000, 60.0


def serial_rate(study: Study, n: int) -> tuple[float, float, int]:
    """Median CPU seconds per run, serial runs per second (wall) and failed runs."""
    cpu: list[float] = []
    failed = 0
    t0 = time.perf_counter()
    for run in range(n):
        c0 = time.process_time()
        try:
            simulate_run(study, run, 0)
        except Exception:
            failed += 1
        cpu.append(time.process_time() - c0)
    return statistics.median(cpu), n / (time.perf_counter() - t0), failed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small CI smoke run")
    parser.add_argument(
        "--methods", default=None, help="comma-separated (default: all; quick: uwb)"
    )
    parser.add_argument("--serial-runs", type=int, default=None)
    parser.add_argument("--dask-runs", type=int, default=None)
    parser.add_argument(
        "--no-target", action="store_true", help="skip the 1,000-run UWB target check"
    )
    parser.add_argument(
        "--fidelity", default="sensors,covariance", help="comma-separated: sensors, covariance"
    )
    args = parser.parse_args()
    fidelities = args.fidelity.split(",")
    methods = (args.methods or ("uwb" if args.quick else "uwb,total_station,icp")).split(",")
    n_serial = args.serial_runs or (3 if args.quick else 10)
    n_dask = args.dask_runs or (4 if args.quick else 100)

    console = Console(width=160)
    project = load_project(SMALL if args.quick else CABIN)
    t0 = time.perf_counter()
    elements = generate_elements(project.elements, project.path)
    plan = plan_project(project, elements)
    prep_s = time.perf_counter() - t0
    studies: dict[str, Study] = {}
    for fidelity in fidelities:
        for m in methods:
            label = m if fidelity == "sensors" else f"{m} ({fidelity})"
            t0 = time.perf_counter()
            try:
                studies[label] = prepare_study(project, m, elements, plan, fidelity)  # type: ignore[arg-type]
            except FabflowError as exc:
                console.print(f"{label}: skipped, {exc}")
                continue
            if fidelity != "sensors":
                console.print(f"{label}: calibrated in {time.perf_counter() - t0:.1f} s")
    base = next(iter(studies.values()))
    console.print(
        f"{project.name}: {base.n_elements} robot-built elements, {base.n_visits} visits; "
        f"elements + plan once: {prep_s:.1f} s"
    )
    for study in studies.values():  # warm caches (site scene, imports) outside the timing
        try:
            simulate_run(study, 0, 0)
        except Exception:
            continue

    table = Table(title=f"simulated runs of {project.name} (every visit localized, all placed)")
    for col in (
        "method",
        "CPU s / run (median)",
        "serial runs/s",
        "Dask 2 workers runs/s",
        "speed-up",
        "1000 runs on Dask (projected s)",
        "failed",
        "p95 mm",
        "within tol",
        "sigma ratio xy",
    ):
        table.add_column(col, justify="left" if col == "method" else "right")
    with dask_client(None, n_workers=2) as client:
        # start-up (worker imports, sending the study) is not part of the rate
        for study in studies.values():
            run_study(study, 2, seed=99, client=client, chunk_size=1)
        for method, study in studies.items():
            scale = 1 if study.fidelity == "sensors" else 20  # surrogate runs take ms
            cpu, rate, failed = serial_rate(study, n_serial * scale)
            result = run_study(study, n_dask * scale, seed=1, client=client)
            dask_rate = n_dask * scale / result.elapsed_s
            row = comparison_row(summarize(study, result))
            table.add_row(
                method,
                f"{cpu:.3f}",
                f"{rate:.2f}",
                f"{dask_rate:.2f}",
                f"{dask_rate / rate:.2f}x",
                f"{TARGET_RUNS / dask_rate:.0f}",
                f"{failed}/{n_serial * scale} serial, {len(result.failures)}/{n_dask * scale} Dask",
                f"{1e3 * row['p95_m']:.1f}",
                f"{100 * row['within_tolerance']:.1f} %",
                f"{row['sigma_ratio_xy']:.2f}",
            )
        console.print(table)
        for label in ("uwb (covariance)", "uwb"):
            if label not in studies or (args.no_target and label == "uwb"):
                continue
            n = 20 if args.quick else TARGET_RUNS
            result = run_study(studies[label], n, seed=2, client=client)
            verdict = "met" if result.elapsed_s < TARGET_S else "NOT met"
            console.print(
                f"{n} {label} runs of {project.name} on 2 workers: {result.elapsed_s:.1f} s "
                f"({len(result.failures)} failed)"
                + ("" if args.quick else f"; target < {TARGET_S:.0f} s: {verdict}")
            )


if __name__ == "__main__":
    main()
