"""Monte Carlo simulation benchmark: simulated construction runs of the cabin per second.

Prints, for each localization method, the CPU time of one run (median), runs per
second serially (in this process) and on a local Dask cluster of 2 single-threaded
worker processes, and the projected time of 1,000 runs; then (full mode) times
1,000 UWB runs of the cabin on the cluster against the 30 s target (issue 25).
The elements and the plan are computed once (not timed), as ``fabflow simulate``
does. ``--breakdown N`` first times the parts of a UWB run (the simulated
ranging; the cleaning, the NLOS correction and the start fixes, each one call
for all the visits; the platform fixes and, within them, the mirror checks and
the hidden-mirror search) over N serial runs.

Run: ``.venv/bin/python benchmarks/simulate.py [--quick] [--methods uwb,total_station,icp]
[--breakdown N]``. ``--quick`` (CI smoke run) simulates a few UWB runs of the
small test project (``tests/data/sim``: four task points, one station) serially
and on 2 workers, with a breakdown of 2 runs.
"""

from __future__ import annotations

import argparse
import importlib
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
TARGET_RUNS, TARGET_S = 1000, 30.0
BREAKDOWN = (
    ("fabflow.localize.uwb", "simulate_station", "ranging simulated (anchors, occlusion, noise)"),
    ("fabflow.localize.uwb_static", "reject_outliers_static", "cleaning of each link (all visits)"),
    ("fabflow.localize.uwb_static", "without_nlos_leak", "the kept NLOS ranges' bias (all visits)"),
    ("fabflow.localize.uwb_static", "median_seeds", "the tags' start fixes (all visits)"),
    ("fabflow.localize.uwb_static", "locate_platforms", "the platform fixes with their tests"),
    ("fabflow.positioning.uwb_platform", "finish_mirror_searches", "  their mirror checks"),
    (
        "fabflow.positioning.uwb_platform",
        "hidden_mirrors_batch",
        "    mirrors one anchor's bias selects",
    ),
)
"""Parts of a UWB run timed by ``--breakdown``: (module, function, what it does); an
indented one is within the one above it."""


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


def breakdown(study: Study, n: int) -> list[tuple[str, float]]:
    """Wall seconds per run of each part of :data:`BREAKDOWN` (and of the whole run),
    over ``n`` serial runs: each function is wrapped in a timer while they run."""
    spent = {name: 0.0 for _, name, _ in BREAKDOWN}
    originals = []
    for module_name, name, _ in BREAKDOWN:
        module = importlib.import_module(module_name)
        original = getattr(module, name)
        originals.append((module, name, original))

        def timed(*a: object, _f=original, _n=name, **k: object) -> object:
            t0 = time.perf_counter()
            try:
                return _f(*a, **k)
            finally:
                spent[_n] += time.perf_counter() - t0

        setattr(module, name, timed)
    try:
        simulate_run(study, 0, 0)
        for v in spent:
            spent[v] = 0.0
        t0 = time.perf_counter()
        for run in range(n):
            simulate_run(study, run, 0)
        total = time.perf_counter() - t0
    finally:
        for module, name, original in originals:
            setattr(module, name, original)
    return [("whole run", total / n)] + [(what, spent[name] / n) for _, name, what in BREAKDOWN]


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
    parser.add_argument(
        "--breakdown",
        type=int,
        default=0,
        metavar="N",
        help="time the parts of a UWB run (sensors fidelity) over N serial runs",
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
    n_breakdown = args.breakdown or (2 if args.quick else 0)
    if n_breakdown and "uwb" in studies:
        parts = breakdown(studies["uwb"], n_breakdown)
        table = Table(title=f"where a UWB run of {project.name} goes ({n_breakdown} runs)")
        for col in ("part", "ms / run", "share"):
            table.add_column(col, justify="left" if col == "part" else "right")
        for what, seconds in parts:
            table.add_row(what, f"{1e3 * seconds:.1f}", f"{100 * seconds / parts[0][1]:.0f} %")
        console.print(table)
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
