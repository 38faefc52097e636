"""Monte Carlo study of a stone wall: registration, grasps and placement over many runs.

Each run draws a new stockpile (stone shapes, sizes, positions, the terrain)
and new sensor noise from the study seed plus the run number, builds the wall
(:func:`fabflow.stones.run.run_stone_wall`) and scores it against the simulated
truth:

* **registration success** (paper 002, section 6.2): the vision map's
  registration was accepted (ICP RMSE below ``e*_icp`` = 3 cm) and every stone
  was segmented as exactly one object;
* **registration time**: wall time of the segment-based registration, both maps'
  segmentation included (the paper's Table 1 total, about 1 s);
* **grasp success** of the best-ranked reachable grasp, by the criterion of
  :mod:`fabflow.manipulation.grasp_check` (collision-free, antipodal within the
  friction cone, held through the lift), over the grasps executed, as the paper
  counts its attempts. A stone without a reachable grasp is not attempted: the
  slot takes the next stone (:func:`~fabflow.stones.run.run_stone_wall`), and
  the study reports those stones and the **slots filled** beside it;
* **placement error**: distance from a stone's true centre of mass after its
  release to where the plan put its model's centroid, over the stones whose
  grasp held (a dropped stone has no placement).

Paper 002's figures: registration 90 % successful in about 1 s; 88.6 % of 35
grasps successful.
"""

from __future__ import annotations

import csv
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fabflow.output import write_json
from fabflow.project import Project
from fabflow.sim.cluster import environment, run_checked
from fabflow.stones.run import StoneRun, run_stone_wall

if TYPE_CHECKING:
    from distributed import Client

PAPER = {
    "registration_success": 0.90,
    "registration_time_s_median": 1.0,
    "grasp_success": 0.886,
}
"""Paper 002's results (section 6.2, Table 1, section 6.3)."""


def run_row(run: StoneRun, index: int) -> dict[str, Any]:
    """One run's figures (``runs.csv``)."""
    attempts = [p for p in run.picks if p.T_grasp is not None]
    held = [p for p in attempts if p.outcome is not None and p.outcome.success]
    unfilled_for_grasp = [p for p in run.picks if p.T_grasp is None and p.object_id >= 0]
    errors = [p.placement_error for p in held]
    return {
        "run": index,
        "objects": len(run.perception.db),
        "stones": len(run.site.T_world_stone),
        "registration_success": run.registration_success,
        "registration_time_s": run.perception.registration_time_s,
        "registration_error_m": run.registration_error_m,
        "slots": len(run.picks),
        "grasp_attempts": len(attempts),
        "grasps_held": len(held),
        "stones_without_grasp": sum(len(p.passed_over) for p in run.picks)
        + len(unfilled_for_grasp),
        "placement_errors_m": errors,
    }


def one_run(project: Project, seed: int, index: int) -> dict[str, Any]:
    """Run number ``index`` of a study seeded ``seed``: its :func:`run_row`."""
    return run_row(run_stone_wall(project, seed=seed + index), index)


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The study's figures under ``stones`` (module docstring), beside the paper's."""
    attempts = sum(r["grasp_attempts"] for r in rows)
    slots = sum(r["slots"] for r in rows)
    errors = np.array([e for r in rows for e in r["placement_errors_m"]])
    times = np.array([r["registration_time_s"] for r in rows])
    return {
        "runs": len(rows),
        "registration_success": float(np.mean([r["registration_success"] for r in rows])),
        "registration_time_s_median": float(np.median(times)),
        "grasp_attempts": attempts,
        "grasp_success": sum(r["grasps_held"] for r in rows) / attempts if attempts else 0.0,
        "stones_without_grasp": sum(r["stones_without_grasp"] for r in rows),
        "slots_filled": sum(r["grasps_held"] for r in rows) / slots if slots else 0.0,
        "placement_error_m": {
            "rmse": float(np.sqrt(np.mean(errors**2))) if len(errors) else None,
            "max": float(errors.max()) if len(errors) else None,
            "stones": len(errors),
        },
        "paper": PAPER,
    }


def simulate_stones(
    project: Project,
    out: Path,
    n_runs: int,
    seed: int,
    progress: Callable[[int], None] | None = None,
    client: Client | None = None,
) -> dict[str, Any]:
    """Run the study; write ``runs.csv`` and ``summary.json`` into ``out``.

    Parameters
    ----------
    project
        A stone wall project.
    out
        The (staging) output folder.
    n_runs
        Runs.
    seed
        Study seed: run ``k`` draws its site and noise from ``seed + k``.
    progress
        Called with 1 after each run.
    client
        A Dask client to run on (one task per run; the results do not depend on
        where a run ran, and a worker with other versions than this machine's is
        refused: :func:`fabflow.sim.cluster.run_checked`); ``None`` runs them here,
        one after the other.

    Returns
    -------
    dict
        ``summary.json``'s content: ``{"project", "seed", "stones": summarize(...)}``.
    """
    rows = []
    if client is None:
        for k in range(n_runs):
            rows.append(one_run(project, seed, k))
            if progress is not None:
                progress(1)
    else:
        from distributed import as_completed

        here = environment()
        futures = [
            client.submit(run_checked, here, one_run, project, seed, k, pure=False)
            for k in range(n_runs)
        ]
        for future in as_completed(futures):
            rows.append(future.result())
            if progress is not None:
                progress(1)
        rows.sort(key=lambda r: r["run"])
    with (out / "runs.csv").open("w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        keys = [k for k in rows[0] if k != "placement_errors_m"]
        writer.writerow([*keys, "placement_error_max_m"])
        for r in rows:
            worst = max(r["placement_errors_m"], default=float("nan"))
            writer.writerow([r[k] for k in keys] + [worst])
    summary = {"project": project.name, "seed": seed, "stones": summarize(rows)}
    write_json(out / "summary.json", summary)
    return summary


def stone_table_rows(summary: dict[str, Any]) -> list[tuple[str, str, str]]:
    """``(figure, simulated, paper)`` rows for the console table and the benchmark."""
    s = summary["stones"]
    pe = s["placement_error_m"]
    return [
        ("registration success", f"{100 * s['registration_success']:.0f} %", "90 %"),
        ("registration time (median)", f"{s['registration_time_s_median']:.2f} s", "about 1 s"),
        (
            "grasp success (best-ranked)",
            f"{100 * s['grasp_success']:.1f} % of {s['grasp_attempts']}",
            "88.6 % of 35",
        ),
        (
            "slots filled (stone held)",
            f"{100 * s['slots_filled']:.1f} %",
            "-",
        ),
        (
            "stones without a reachable grasp",
            f"{s['stones_without_grasp']} (passed over)",
            "-",
        ),
        (
            "placement error RMSE / max",
            "-" if pe["rmse"] is None else f"{1e3 * pe['rmse']:.0f} / {1e3 * pe['max']:.0f} mm",
            "-",
        ),
    ]
