"""Monte Carlo tolerance studies: many seeded simulated runs, serially or on Dask.

Runs are grouped into chunks (one Dask task each, so scheduling overhead stays
small next to the runs); the prepared :class:`~fabflow.sim.run.Study`, with the
data of the files it reads, is sent to every worker once, and every task checks
that its worker runs this machine's versions (:mod:`fabflow.sim.cluster`). A
run that raises is recorded as a :class:`RunFailure` with its seed and error and
listed in ``summary.json``; it is never silently dropped.
Results do not depend on how runs are chunked or where they execute: run ``i``
always draws from ``SeedSequence(seed, spawn_key=(i,))``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import special

from fabflow.errors import UnsupportedError
from fabflow.positioning.result import BasePose
from fabflow.sim.cluster import dask_client as dask_client  # where it was, for callers
from fabflow.sim.cluster import environment, run_checked
from fabflow.sim.cluster import scheduler_address as scheduler_address
from fabflow.sim.run import STATUSES, UNOBSERVED_SIGMA, RunResult, Study, simulate_run

if TYPE_CHECKING:
    from distributed import Client


AXES = ("x", "y", "z", "rx", "ry", "rz")


@dataclass(frozen=True)
class RunFailure:
    """A run that raised: its index, the study seed and the error message."""

    run: int
    seed: int
    error: str


def simulate_chunk(
    study: Study, runs: Sequence[int], seed: int, keep_first: bool = False
) -> list[RunResult | RunFailure]:
    """Simulate several runs; a run that raises becomes a :class:`RunFailure`.

    Parameters
    ----------
    study
        The prepared study.
    runs
        Run indices.
    seed
        Study seed.
    keep_first
        Keep the base pose estimates and as-built poses of run 0 (written to the output).
    """
    out: list[RunResult | RunFailure] = []
    for run in runs:
        try:
            out.append(simulate_run(study, run, seed, keep_poses=keep_first and run == 0))
        except Exception as exc:
            out.append(RunFailure(run=run, seed=seed, error=f"{type(exc).__name__}: {exc}"))
    return out


@dataclass(frozen=True, eq=False)
class StudyResult:
    """All runs of one study (one localization method), stacked.

    Attributes
    ----------
    method
        Localization method.
    seed
        Study seed.
    n_runs
        Runs requested.
    runs
        (R,) indices of the runs that completed, ascending.
    translation_m, rotation_rad
        (R, N) per run and element deviation (metres, radians).
    deviation_xyz
        (R, N, 3) as-built minus planned element origin (metres, world frame).
    localization_error
        (R, V, 6) base pose error per run and visit (true minus estimate).
    localization_covariance
        (R, V, 6, 6) predicted covariance per run and visit.
    failures
        Runs that raised.
    base_poses
        The base pose estimates of run 0 (empty if it failed).
    T_world_element_asbuilt_run0
        (N, 4, 4) as-built element poses of run 0 (``None`` if it failed).
    elapsed_s
        Wall-clock time of the runs (seconds).
    integrity
        (R, V) integrity status per run and visit (index into
        :data:`fabflow.sim.run.STATUSES`).
    """

    method: str
    seed: int
    n_runs: int
    runs: np.ndarray
    translation_m: np.ndarray
    rotation_rad: np.ndarray
    deviation_xyz: np.ndarray
    localization_error: np.ndarray
    localization_covariance: np.ndarray
    failures: tuple[RunFailure, ...]
    base_poses: tuple[BasePose, ...]
    T_world_element_asbuilt_run0: np.ndarray | None
    elapsed_s: float
    integrity: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int8))


def collect(
    study: Study, seed: int, n_runs: int, items: Sequence[RunResult | RunFailure], elapsed: float
) -> StudyResult:
    """Stack run results (any order) into a :class:`StudyResult`."""
    ok = sorted((r for r in items if isinstance(r, RunResult)), key=lambda r: r.run)
    failures = tuple(sorted((r for r in items if isinstance(r, RunFailure)), key=lambda r: r.run))
    N, V = study.n_elements, study.n_visits

    def stack(name: str, shape: tuple[int, ...]) -> np.ndarray:
        if not ok:
            return np.zeros((0, *shape))
        return np.stack([getattr(r, name) for r in ok])

    first = next((r for r in ok if r.run == 0), None)
    return StudyResult(
        method=study.name,
        seed=seed,
        n_runs=n_runs,
        runs=np.array([r.run for r in ok], dtype=np.intp),
        translation_m=stack("translation_m", (N,)),
        rotation_rad=stack("rotation_rad", (N,)),
        deviation_xyz=stack("deviation_xyz", (N, 3)),
        localization_error=stack("localization_error", (V, 6)),
        localization_covariance=stack("localization_covariance", (V, 6, 6)),
        failures=failures,
        base_poses=first.base_poses if first is not None else (),
        T_world_element_asbuilt_run0=None if first is None else first.T_world_element_asbuilt,
        elapsed_s=elapsed,
        integrity=stack("integrity", (V,)).astype(np.int8),
    )


def default_chunk_size(n_runs: int, n_workers: int) -> int:
    """Runs per task: about eight tasks per worker (load balance, progress), at most 50."""
    return max(1, min(50, math.ceil(n_runs / (8 * max(1, n_workers)))))


def run_study(
    study: Study,
    n_runs: int,
    seed: int,
    client: Client | None = None,
    chunk_size: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> StudyResult:
    """Run ``n_runs`` seeded runs of a study, serially or on a Dask cluster.

    Parameters
    ----------
    study
        The prepared study.
    n_runs
        Number of runs (run indices ``0 .. n_runs - 1``).
    seed
        Study seed.
    client
        A ``dask.distributed`` client; ``None`` runs everything in this process.
    chunk_size
        Runs per task (default :func:`default_chunk_size`).
    progress
        Called with the number of runs just finished, as chunks complete.
    """
    t0 = time.perf_counter()
    if client is None:
        size = chunk_size or default_chunk_size(n_runs, 1)
    else:
        size = chunk_size or default_chunk_size(n_runs, len(client.scheduler_info()["workers"]))
    chunks = [list(range(i, min(i + size, n_runs))) for i in range(0, n_runs, size)]
    items: list[RunResult | RunFailure] = []
    if client is None:
        for chunk in chunks:
            items += simulate_chunk(study, chunk, seed, keep_first=True)
            if progress is not None:
                progress(len(chunk))
        return collect(study, seed, n_runs, items, time.perf_counter() - t0)

    from distributed import as_completed

    [study_future] = client.scatter([study], broadcast=True, hash=False)
    here = environment()
    futures = {
        client.submit(
            run_checked, here, simulate_chunk, study_future, chunk, seed, True, pure=False
        ): chunk
        for chunk in chunks
    }
    for future in as_completed(futures):
        chunk = futures[future]
        if future.status == "error":
            exc = future.exception()
            if isinstance(exc, UnsupportedError):  # a worker with other versions
                client.cancel(list(futures))
                raise exc
            error = f"task failed: {type(exc).__name__}: {exc}"
            items += [RunFailure(run=r, seed=seed, error=error) for r in chunk]
        else:
            items += future.result()
        if progress is not None:
            progress(len(chunk))
    return collect(study, seed, n_runs, items, time.perf_counter() - t0)


# ----------------------------------------------------------------------- statistics


def _stats(values: np.ndarray) -> dict[str, float]:
    v = np.asarray(values, dtype=float).ravel()
    if v.size == 0:
        return {"rmse": math.nan, "mean": math.nan, "p95": math.nan, "max": math.nan}
    return {
        "rmse": float(np.sqrt(np.mean(v**2))),
        "mean": float(np.mean(v)),
        "p95": float(np.percentile(v, 95)),
        "max": float(np.max(v)),
    }


def within_tolerance(study: Study, result: StudyResult) -> np.ndarray:
    """(R, N) whether each as-built element is within the project's tolerances."""
    tol = study.project.tolerances
    return (result.translation_m <= tol.position) & (
        result.rotation_rad <= math.radians(tol.rotation_deg)
    )


def sigma_ratio(errors: np.ndarray, covariances: np.ndarray) -> dict[str, float]:
    """Empirical RMS error over predicted RMS sigma, per observed axis.

    1 means the predicted covariance is honest, above 1 over-confident, below 1
    pessimistic. Axes with a predicted sigma of at least :data:`UNOBSERVED_SIGMA` are
    not observed by the method and are left out, as are axes predicted exact (zero).

    Parameters
    ----------
    errors
        (..., 6) pose errors.
    covariances
        (..., 6, 6) predicted covariances.
    """
    e = errors.reshape(-1, 6)
    sigma = np.sqrt(np.clip(np.diagonal(covariances, axis1=-2, axis2=-1), 0.0, None))
    sigma = sigma.reshape(-1, 6)
    out: dict[str, float] = {}
    for k, axis in enumerate(AXES):
        if e.shape[0] == 0 or np.any(sigma[:, k] >= UNOBSERVED_SIGMA):
            continue
        predicted = float(np.sqrt(np.mean(sigma[:, k] ** 2)))
        if predicted < 1e-12:  # predicted exact (no sensor noise, or an axis held fixed)
            continue
        out[axis] = float(np.sqrt(np.mean(e[:, k] ** 2))) / predicted
    return out


def _localization_stats(errors: np.ndarray, covariances: np.ndarray) -> dict[str, Any]:
    e = errors.reshape(-1, 6)
    sigma = np.sqrt(np.clip(np.diagonal(covariances, axis1=-2, axis2=-1), 0.0, None))
    sigma = sigma.reshape(-1, 6)
    xy = np.linalg.norm(e[:, :2], axis=1)
    return {
        "visits": int(e.shape[0]),
        "xy_error_m": _stats(xy),
        "rmse": {
            a: float(np.sqrt(np.mean(e[:, k] ** 2))) if len(e) else math.nan
            for k, a in enumerate(AXES)
        },
        "predicted_sigma": {
            a: float(np.sqrt(np.mean(sigma[:, k] ** 2))) if len(e) else math.nan
            for k, a in enumerate(AXES)
        },
        "sigma_ratio": sigma_ratio(errors, covariances),
    }


def summarize(study: Study, result: StudyResult) -> dict[str, Any]:
    """The ``summary.json`` content of one study: overall, per station, localization.

    Translation figures are metres, rotation figures radians; ``within_tolerance`` is
    the share of element placements (over all runs) within both tolerances of the
    project.
    """
    ok = within_tolerance(study, result)
    tol = study.project.tolerances
    stations = [s.id for s in study.stations]
    per_station: dict[str, Any] = {}
    for sid in dict.fromkeys(stations):
        cols = np.flatnonzero(np.array(study.element_station) == sid)
        visits = [v for v, s in enumerate(stations) if s == sid]
        per_station[sid] = {
            "elements": len(cols),
            "visits": len(visits),
            "translation_m": _stats(result.translation_m[:, cols]),
            "rotation_rad": _stats(result.rotation_rad[:, cols]),
            "within_tolerance": float(ok[:, cols].mean()) if ok[:, cols].size else math.nan,
            "localization": _localization_stats(
                result.localization_error[:, visits], result.localization_covariance[:, visits]
            ),
        }
    run_rmse = (
        np.sqrt(np.mean(result.translation_m**2, axis=1)) if result.runs.size else np.zeros(0)
    )
    return {
        "method": result.method,
        "fidelity": study.fidelity,
        "seed": result.seed,
        "runs": {
            "requested": result.n_runs,
            "completed": int(result.runs.size),
            "failed": len(result.failures),
            "elapsed_s": result.elapsed_s,
        },
        "failures": [{"run": f.run, "seed": f.seed, "error": f.error} for f in result.failures],
        "elements": study.n_elements,
        "visits": study.n_visits,
        "tolerances": {"position_m": tol.position, "rotation_rad": math.radians(tol.rotation_deg)},
        "translation_m": _stats(result.translation_m),
        "rotation_rad": _stats(result.rotation_rad),
        "within_tolerance": float(ok.mean()) if ok.size else math.nan,
        "within_position_tolerance": float((result.translation_m <= tol.position).mean())
        if ok.size
        else math.nan,
        "runs_all_within_tolerance": float(ok.all(axis=1).mean()) if ok.size else math.nan,
        "run_rmse_m": _stats(run_rmse),
        "localization": _localization_stats(
            result.localization_error, result.localization_covariance
        ),
        "integrity": integrity_stats(result),
        "per_station": per_station,
        **({"setups": setup_drift(study, result)} if study.setups else {}),
    }


def setup_drift(study: Study, result: StudyResult) -> list[dict[str, Any]]:
    """Per total station set-up, in build order: the XY error of the base at the visits
    it localized (mean and max over runs and visits, metres). With set-ups registered on
    the robot's prisms (Procedure A) the error grows from set-up to set-up; on control
    points (Procedure B) it does not (paper 001, Fig 7)."""
    assert study.setups is not None
    xy = np.linalg.norm(result.localization_error[..., :2], axis=-1)  # (R, V)
    out = []
    for s in study.setups:
        e = xy[:, list(s.packages)]
        out.append(
            {
                "id": s.id,
                "packages": [s.packages[0] + 1, s.packages[-1] + 1],
                "registration": s.registration,
                "position": s.T_world_instrument[:3, 3].tolist(),
                "xy_error_m": {
                    "mean": float(e.mean()) if e.size else math.nan,
                    "max": float(e.max()) if e.size else math.nan,
                },
            }
        )
    return out


def integrity_stats(result: StudyResult) -> dict[str, Any]:
    """How the visits' integrity tests did against the truth the simulation knows.

    A visit is *wrong* when its true error lies outside the 99.9 % ellipsoid of
    its predicted covariance (over the observed axes). Against the status:
    ``detected`` = wrong and failed; ``false_alarms`` = failed but not wrong;
    ``silently_wrong`` = wrong with status ok or excluded (what must not happen);
    ``excluded`` = passed after leaving observations out.
    """
    status = result.integrity.reshape(-1)
    if status.size == 0:
        return {"visits": 0}
    e = result.localization_error.reshape(-1, 6)
    C = result.localization_covariance.reshape(-1, 6, 6)
    sigma = np.sqrt(np.clip(np.diagonal(C, axis1=-2, axis2=-1), 0.0, None))
    observed = np.all(sigma < UNOBSERVED_SIGMA, axis=0) & np.any(sigma > 0, axis=0)
    k = int(observed.sum())
    wrong = np.zeros(len(e), dtype=bool)
    if k:
        Co = C[:, observed][:, :, observed]
        eo = e[:, observed]
        d2 = np.einsum(
            "ni,ni->n", eo, np.linalg.solve(Co + 1e-30 * np.eye(k), eo[..., None])[..., 0]
        )
        wrong = d2 > float(special.chdtri(k, 1e-3))
    tested = status != STATUSES.index("untested")
    failed = status == STATUSES.index("failed")
    return {
        "visits": int(status.size),
        "tested": int(tested.sum()),
        **{name: int((status == i).sum()) for i, name in enumerate(STATUSES)},
        "detected": int((failed & wrong).sum()),
        "false_alarms": int((failed & ~wrong).sum()),
        "silently_wrong": int((tested & ~failed & wrong).sum()),
        "wrong": int(wrong.sum()),
    }


def comparison_row(summary: dict[str, Any]) -> dict[str, Any]:
    """One row of the method comparison table from a study summary."""
    loc = summary["localization"]
    ratio = loc["sigma_ratio"]
    return {
        "method": summary["method"],
        "runs_completed": summary["runs"]["completed"],
        "runs_failed": summary["runs"]["failed"],
        "rmse_m": summary["translation_m"]["rmse"],
        "p95_m": summary["translation_m"]["p95"],
        "max_m": summary["translation_m"]["max"],
        "rotation_p95_rad": summary["rotation_rad"]["p95"],
        "within_tolerance": summary["within_tolerance"],
        "runs_all_within_tolerance": summary["runs_all_within_tolerance"],
        "localization_xy_rmse_m": loc["xy_error_m"]["rmse"],
        "sigma_ratio_xy": float(np.sqrt(np.mean([ratio[a] ** 2 for a in ("x", "y")])))
        if {"x", "y"} <= ratio.keys()
        else math.nan,
        "seconds_per_run": summary["runs"]["elapsed_s"] / max(1, summary["runs"]["requested"]),
        "setups": summary.get("setups"),
        "visits_failed": summary["integrity"].get("failed", 0),
        "silently_wrong": summary["integrity"].get("silently_wrong", 0),
    }
