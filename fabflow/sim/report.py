"""Files of a ``fabflow simulate`` output folder, and the whole study driver.

One localization method writes into one folder:

* ``elements.csv``: one row per robot-built element, aggregated over the runs:
  ``deviation_m`` (mean translational deviation, the column ``fabflow preview --sim``
  colours by), ``p95_translation_m``, ``max_translation_m``, ``mean_rotation_rad``,
  ``p95_rotation_rad``, the mean deviation vector and the share within tolerance;
* ``runs.csv``: one row per run (seed, status, RMSE, p95, max, share within
  tolerance, or the error of a failed run);
* ``visits.csv``: one row per run and visit: the base pose error (true minus
  estimate) and the predicted sigma of every axis;
* ``summary.json``: :func:`fabflow.sim.monte_carlo.summarize`;
* ``deviation_histogram.png``, ``deviation_heat_map.png``, ``localization_error.png``;
* ``asbuilt_run0.csv``: planned and as-built pose of every element in run 0
  (x, y, z in metres, KUKA A, B, C in degrees) and its deviation;
* ``localization/visit_NN_STATION.json``: the base pose estimates of run 0.

Several methods write one such folder each (``OUT/<method>/``) plus
``OUT/comparison.csv`` and ``OUT/summary.json`` (all methods).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fabflow.design.generate import generate_elements
from fabflow.errors import InputError, LocalizationError
from fabflow.output import write_json
from fabflow.project import LOCALIZATION_METHODS, Project
from fabflow.sim.monte_carlo import (
    AXES,
    RunFailure,
    StudyResult,
    collect,
    comparison_row,
    run_study,
    summarize,
    within_tolerance,
)
from fabflow.sim.plots import write_plots
from fabflow.sim.run import (
    CALIBRATION_RUNS,
    STATUSES,
    Fidelity,
    Study,
    calibrate_covariance,
    prepare_study,
)
from fabflow.tasks.planner import plan_project
from fabflow.transforms.so3 import abc_from_matrix
from fabflow.version import __version__

if TYPE_CHECKING:
    from distributed import Client


def _fmt(value: Any) -> Any:
    if isinstance(value, float | np.floating):
        return "" if math.isnan(value) else f"{float(value):.6g}"
    return value


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> Path:
    with path.open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows([[_fmt(v) for v in row] for row in rows])
    return path


def element_rows(study: Study, result: StudyResult) -> tuple[list[str], list[list[Any]]]:
    """Header and rows of ``elements.csv`` (per-element aggregates over the runs)."""
    header = [
        "element",
        "station",
        "visit",
        "x_m",
        "y_m",
        "z_m",
        "deviation_m",
        "p95_translation_m",
        "max_translation_m",
        "mean_rotation_rad",
        "p95_rotation_rad",
        "mean_dx_m",
        "mean_dy_m",
        "mean_dz_m",
        "within_tolerance",
    ]
    N = study.n_elements
    if result.runs.size:
        t, r = result.translation_m, result.rotation_rad
        cols = [
            t.mean(0),
            np.percentile(t, 95, axis=0),
            t.max(0),
            r.mean(0),
            np.percentile(r, 95, axis=0),
            *result.deviation_xyz.mean(0).T,
            within_tolerance(study, result).mean(0),
        ]
    else:
        cols = [np.full(N, math.nan)] * 9
    xyz = study.T_world_element[:, :3, 3]
    rows = [
        [eid, study.stations[v].id, int(v) + 1, *xyz[i], *(c[i] for c in cols)]
        for i, (eid, v) in enumerate(zip(study.element_ids, study.element_visit, strict=True))
    ]
    return header, rows


def run_rows(study: Study, result: StudyResult) -> tuple[list[str], list[list[Any]]]:
    """Header and rows of ``runs.csv`` (one per requested run, failed ones included)."""
    header = [
        "run",
        "seed",
        "status",
        "rmse_m",
        "p95_m",
        "max_m",
        "max_rotation_rad",
        "within_tolerance",
        "error",
    ]
    ok = within_tolerance(study, result)
    rows: list[list[Any]] = []
    for k, run in enumerate(result.runs):
        t = result.translation_m[k]
        rows.append(
            [
                int(run),
                result.seed,
                "ok",
                float(np.sqrt(np.mean(t**2))) if t.size else math.nan,
                float(np.percentile(t, 95)) if t.size else math.nan,
                float(t.max()) if t.size else math.nan,
                float(result.rotation_rad[k].max()) if t.size else math.nan,
                float(ok[k].mean()) if t.size else math.nan,
                "",
            ]
        )
    for f in result.failures:
        rows.append([f.run, f.seed, "failed", *[math.nan] * 5, f.error])
    rows.sort(key=lambda row: row[0])
    return header, rows


def asbuilt_rows(study: Study, result: StudyResult) -> tuple[list[str], list[list[Any]]]:
    """Header and rows of ``asbuilt_run0.csv``: planned vs as-built pose in run 0.

    The deviation columns are named ``run0_*`` so that ``fabflow preview --sim``
    (which averages every deviation column it knows) does not mix them in.
    """
    pose = ["x_m", "y_m", "z_m", "a_deg", "b_deg", "c_deg"]
    header = [
        "element",
        "station",
        *(f"planned_{c}" for c in pose),
        *(f"asbuilt_{c}" for c in pose),
        "run0_translation_m",
        "run0_rotation_rad",
    ]
    T_asbuilt = result.T_world_element_asbuilt_run0
    if T_asbuilt is None:
        return header, []
    k = int(np.flatnonzero(result.runs == 0)[0])

    def xyzabc(T: np.ndarray) -> np.ndarray:
        return np.column_stack([T[:, :3, 3], np.degrees(abc_from_matrix(T[:, :3, :3]))])

    planned, built = xyzabc(study.T_world_element), xyzabc(T_asbuilt)
    rows = [
        [
            eid,
            study.stations[v].id,
            *planned[i],
            *built[i],
            result.translation_m[k, i],
            result.rotation_rad[k, i],
        ]
        for i, (eid, v) in enumerate(zip(study.element_ids, study.element_visit, strict=True))
    ]
    return header, rows


def visit_rows(study: Study, result: StudyResult) -> tuple[list[str], list[list[Any]]]:
    """Header and rows of ``visits.csv`` (base pose error and predicted sigma per visit)."""
    units = ["m"] * 3 + ["rad"] * 3
    header = [
        "run",
        "visit",
        "station",
        *(f"error_{a}_{u}" for a, u in zip(AXES, units, strict=True)),
        *(f"sigma_{a}_{u}" for a, u in zip(AXES, units, strict=True)),
        "integrity",
    ]
    sigma = np.sqrt(
        np.clip(np.diagonal(result.localization_covariance, axis1=-2, axis2=-1), 0.0, None)
    )
    rows = [
        [
            int(run),
            v + 1,
            s.id,
            *result.localization_error[k, v],
            *sigma[k, v],
            STATUSES[int(result.integrity[k, v])],
        ]
        for k, run in enumerate(result.runs)
        for v, s in enumerate(study.stations)
    ]
    return header, rows


def write_study(
    folder: Path, study: Study, result: StudyResult, plots: bool = True
) -> dict[str, Any]:
    """Write every file of one method's study into ``folder`` (created); return the summary.

    ``plots=False`` leaves out the PNG plots.
    """

    folder.mkdir(parents=True, exist_ok=True)
    _write_csv(folder / "elements.csv", *element_rows(study, result))
    _write_csv(folder / "runs.csv", *run_rows(study, result))
    _write_csv(folder / "visits.csv", *visit_rows(study, result))
    if result.T_world_element_asbuilt_run0 is not None:
        _write_csv(folder / "asbuilt_run0.csv", *asbuilt_rows(study, result))
    summary = {"fabflow_version": __version__, "project": study.project.name}
    summary |= summarize(study, result)
    write_json(folder / "summary.json", summary)
    if plots:
        write_plots(study, result, folder)
    if result.base_poses:
        loc = folder / "localization"
        loc.mkdir(exist_ok=True)
        for v, pose in enumerate(result.base_poses):
            write_json(
                loc / f"visit_{v + 1:02d}_{pose.station}.json",
                {**pose.to_dict(), "visit": v + 1, "simulated": True, "run": 0},
            )
    return summary


def parse_methods(text: str) -> list[str]:
    """Methods from a comma-separated list such as ``"uwb,total_station,icp"``.

    Raises
    ------
    InputError
        For an empty list or an unknown method name.
    """
    names = list(dict.fromkeys(m.strip() for m in text.split(",") if m.strip()))
    unknown = [m for m in names if m not in LOCALIZATION_METHODS]
    if not names or unknown:
        raise InputError(
            f"unknown localization method(s) {', '.join(unknown) or '(none given)'}: "
            f"expected a comma-separated list of {', '.join(LOCALIZATION_METHODS)}",
            location="--methods",
        )
    return names


SETUP_DRIFT_TITLE = (
    "total station set-ups: XY error of the base they localized "
    "(paper 001, Procedure A over 5 set-ups: about 30 mm mean, 70 mm peak)"
)
SETUP_DRIFT_COLUMNS = ("study", "set-up", " packages", "registered on", " mean mm", " max mm")
"""Columns of the set-up table; a leading space marks a right-aligned (numeric) column."""


def setup_drift_rows(rows: Sequence[dict[str, Any]]) -> list[list[str]]:
    """The set-up table's rows (:data:`SETUP_DRIFT_COLUMNS`) from the comparison rows of
    :func:`simulate_project`: per total station study and set-up, the XY error of the
    base at the visits it localized (mean and max over runs, mm)."""
    return [
        [
            r["method"],
            s["id"],
            "{}-{}".format(*s["packages"]),
            s["registration"].replace("_", " "),
            f"{1e3 * s['xy_error_m']['mean']:.1f}",
            f"{1e3 * s['xy_error_m']['max']:.1f}",
        ]
        for r in rows
        for s in r.get("setups") or ()
    ]


def check_runs_completed(rows: Sequence[dict[str, Any]], out: str | Path) -> None:
    """Raise when every run of a method failed (its report, with the errors, is written).

    Parameters
    ----------
    rows
        The comparison rows of :func:`simulate_project`.
    out
        The output folder, named in the message.

    Raises
    ------
    LocalizationError
        Naming each method none of whose runs completed (the CLI exits with 2).
    """
    failed = [r["method"] for r in rows if r["runs_completed"] == 0 and r["runs_failed"] > 0]
    if failed:
        names = ", ".join(f"'{m}'" for m in failed)
        what = "method" if len(failed) == 1 else "methods"
        raise LocalizationError(
            f"every run of {what} {names} failed; the errors are in runs.csv and summary.json",
            source=out,
        )


COMPARISON_COLUMNS = (
    "method",
    "runs_completed",
    "runs_failed",
    "rmse_m",
    "p95_m",
    "max_m",
    "rotation_p95_rad",
    "within_tolerance",
    "runs_all_within_tolerance",
    "localization_xy_rmse_m",
    "sigma_ratio_xy",
    "seconds_per_run",
)


def simulate_project(
    project: Project,
    out: Path,
    n_runs: int,
    seed: int,
    methods: Sequence[str] | None = None,
    client: Client | None = None,
    chunk_size: int | None = None,
    on_method: Callable[[str], None] | None = None,
    progress: Callable[[int], None] | None = None,
    plots: bool = True,
    fidelity: Fidelity = "sensors",
    stationings: Sequence[str] | None = None,
) -> list[dict[str, Any]]:
    """Run a Monte Carlo study per method and write every output into ``out``.

    The elements and the plan are computed once and shared by all methods, so the
    methods are compared on the same stations and seeds.

    Parameters
    ----------
    project
        The validated project.
    out
        An existing, empty folder (the CLI passes an atomic staging folder).
    n_runs, seed
        Runs per method and study seed.
    methods
        Localization methods (default: the project's). One method writes its files
        into ``out``; several write ``out/<method>/`` each.
    client
        A ``dask.distributed`` client, or ``None`` to run serially.
    chunk_size
        Runs per Dask task.
    on_method
        Called with each method's name before its runs start.
    progress
        Called with the number of runs just finished.
    plots
        Write the PNG plots (matplotlib).
    fidelity
        ``"sensors"`` or ``"covariance"`` (see :func:`fabflow.sim.run.prepare_study`).
        A method whose calibration fails (it cannot localize at a planned pose) has
        every run reported failed, with the error; the other methods still run.
    stationings
        For the total station, one study per way of registering its set-ups
        (``control_points``, ``robot_points``: paper 001's Procedures B and A),
        labelled ``total_station-<stationing>``; default the project's.

    Returns
    -------
    list of dict
        The comparison rows (one per method).
    """

    if fidelity not in ("sensors", "covariance"):
        raise InputError(
            f"unknown fidelity {fidelity!r}: expected 'sensors' or 'covariance'",
            location="--fidelity",
        )
    methods = list(methods or [project.localization.method])
    elements = generate_elements(project.elements, project.path, project.limits)
    plan = plan_project(project, elements)
    studies = [
        prepare_study(project, m, elements, plan, stationing=s)
        for m in methods
        for s in (stationings if m == "total_station" and stationings else [None])
    ]
    rows: list[dict[str, Any]] = []
    summaries: dict[str, Any] = {}
    for study in studies:
        if on_method is not None:
            on_method(study.name)
        try:
            if fidelity == "covariance":
                study = replace(
                    study,
                    fidelity="covariance",
                    visit_covariance=calibrate_covariance(study, CALIBRATION_RUNS),
                )
        except LocalizationError as exc:
            # the method cannot localize at a planned pose: every run of it fails
            error = f"covariance calibration failed: {type(exc).__name__}: {exc}"
            failures = [RunFailure(run=r, seed=seed, error=error) for r in range(n_runs)]
            study = replace(study, fidelity="covariance")
            result = collect(study, seed, n_runs, failures, 0.0)
            if progress is not None:
                progress(n_runs)
        else:
            result = run_study(study, n_runs, seed, client, chunk_size, progress)
        folder = out if len(studies) == 1 else out / study.name
        summary = write_study(folder, study, result, plots)
        summaries[study.name] = summary
        rows.append(comparison_row(summary))
    _write_csv(
        out / "comparison.csv",
        COMPARISON_COLUMNS,
        [[row[c] for c in COMPARISON_COLUMNS] for row in rows],
    )
    if len(studies) > 1:
        write_json(
            out / "summary.json",
            {
                "fabflow_version": __version__,
                "project": project.name,
                "runs": n_runs,
                "seed": seed,
                "comparison": rows,
                "methods": summaries,
            },
        )
    return rows
