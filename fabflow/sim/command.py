"""What ``fabflow simulate`` does: run the study on Dask and print its table."""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn
from rich.table import Table

from fabflow.output import atomic_output_dir
from fabflow.project import load_project
from fabflow.sim.cluster import dask_client
from fabflow.sim.report import (
    SETUP_DRIFT_COLUMNS,
    SETUP_DRIFT_TITLE,
    check_runs_completed,
    parse_methods,
    setup_drift_rows,
    simulate_project,
)
from fabflow.sim.stones import simulate_stones, stone_table_rows


def run_simulate(
    project: Path,
    out: Path,
    runs: int | None,
    methods: str | None,
    seed: int | None,
    scheduler: str | None,
    workers: int,
    timeout: float,
    dashboard: bool,
    plots: bool,
    fidelity: str,
    stationing: str | None,
    console: Console,
    scheduler_file: Path | None = None,
) -> None:
    """Run a Monte Carlo study of a project and print its table (the ``simulate`` options).

    ``scheduler_file``: the file of a running Dask scheduler (``--scheduler-file``),
    instead of its address ``scheduler``.
    """
    p = load_project(project)
    chosen = parse_methods(methods) if methods else [p.localization.method]
    n_runs = runs or p.simulation.runs
    columns = ("{task.description}", BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    local = scheduler is None and scheduler_file is None
    in_process = local and workers == 0
    cluster = dask_client(
        scheduler, workers, timeout, dashboard=dashboard, scheduler_file=scheduler_file
    )
    if p.stone_wall() is not None:  # found stones: no stations to localize
        with (
            atomic_output_dir(out) as staging,
            nullcontext(None) if in_process else cluster as client,
            Progress(*columns, console=console) as bar,
        ):
            task = bar.add_task("stone wall runs", total=n_runs)
            study_seed = p.simulation.seed if seed is None else seed
            advance = lambda n: bar.advance(task, n)  # noqa: E731
            summary = simulate_stones(p, staging, n_runs, study_seed, advance, client)
        table = Table(title=f"fabflow simulate: {p.name}, {n_runs} runs")
        for name in ("figure", "simulated", "paper 002"):
            table.add_column(name)
        for row in stone_table_rows(summary):
            table.add_row(*row)
        console.print(table)
        console.print(f"[green]wrote[/] {Path(out).resolve()}")
        return
    with (
        atomic_output_dir(out) as staging,
        nullcontext(None) if in_process else cluster as client,
        Progress(*columns, console=console) as bar,
    ):
        if client is not None and dashboard and local:
            console.print(f"Dask dashboard: {client.dashboard_link}")
        tasks: dict[str, Any] = {}

        def start(method: str) -> None:
            tasks["current"] = bar.add_task(f"{method} runs", total=n_runs)

        rows = simulate_project(
            p,
            staging,
            n_runs,
            p.simulation.seed if seed is None else seed,
            chosen,
            client=client,
            on_method=start,
            progress=lambda n: bar.advance(tasks["current"], n),
            plots=plots,
            fidelity=fidelity,  # type: ignore[arg-type]  # checked by prepare_study
            stationings=stationing.split(",") if stationing else None,
        )
    table = Table(title=f"fabflow simulate: {p.name}, {n_runs} runs ({fidelity})")
    for name in ("method", "runs ok/failed", "RMSE mm", "p95 mm", "max mm", "within tol"):
        table.add_column(name, justify="left" if name == "method" else "right")
    table.add_column("loc. xy RMSE mm", justify="right")
    table.add_column("sigma ratio xy", justify="right")
    table.add_column("visits failed / silently wrong", justify="right")
    for r in rows:
        table.add_row(
            r["method"],
            f"{r['runs_completed']}/{r['runs_failed']}",
            f"{1e3 * r['rmse_m']:.2f}",
            f"{1e3 * r['p95_m']:.2f}",
            f"{1e3 * r['max_m']:.2f}",
            f"{100 * r['within_tolerance']:.1f} %",
            f"{1e3 * r['localization_xy_rmse_m']:.2f}",
            f"{r['sigma_ratio_xy']:.2f}",
            f"{r['visits_failed']} / {r['silently_wrong']}",
        )
    console.print(table)
    drift = setup_drift_rows(rows)
    if drift:
        table = Table(title=SETUP_DRIFT_TITLE)
        for name in SETUP_DRIFT_COLUMNS:
            table.add_column(name, justify="left" if name[0].isalpha() else "right")
        for row in drift:
            table.add_row(*row)
        console.print(table)
    failed = sum(r["runs_failed"] for r in rows)
    if failed:
        console.print(f"[yellow]{failed} run(s) failed: see runs.csv and summary.json[/]")
    console.print(f"[green]wrote[/] {Path(out).resolve()}")
    check_runs_completed(rows, out)
