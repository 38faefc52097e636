"""Integrity benchmark: faults injected per method, and what the tests make of them.

1. Per method and fault kind (``fabflow.sim.faults``), over seeded stations of the
   cabin: injected, detected (the pose failed), refused (no pose at all),
   excluded (and correctly: the faulty observation), silently wrong (passed with
   the true error outside the 99.9 % ellipsoid of its covariance), of which above
   the fault's minimal detectable bias, and the false-alarm rate on clean data.
2. The static UWB estimator on a 5-anchor layout (the paper's four plus one above
   the centre) with 2 % NLOS ranges: mean error of LS, WLS-T and WLS-T with data
   snooping, and on clean data the RMS against the Cramer-Rao bound.

Run: ``.venv/bin/python benchmarks/integrity.py [--quick] [--n 200] [--methods uwb,...]``
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from fabflow.positioning.adjustment_tests import ALPHA
from fabflow.positioning.uwb import crlb, locate
from fabflow.project import load_project
from fabflow.sensors.uwb import UwbErrorModel, simulate_ranges
from fabflow.sim.faults import ELLIPSOID, FAULTS, fault_study, with_method

ROOT = Path(__file__).resolve().parents[1]
ANCHORS_5 = np.array(
    [[0.0, 0.0, 1.0], [4.8, 0.0, 1.0], [4.8, 6.0, 1.0], [0.0, 6.0, 3.2], [2.4, 3.0, 3.2]]
)
POINTS = np.array([[1.0, 1.5, 1.2], [2.4, 3.0, 1.0], [3.8, 4.5, 1.5], [1.5, 4.8, 0.8]])


def projects():
    """(row label, method, project): the cabin localized by each method.

    The total station twice: with the cabin's four prism points (the paper's
    setup) and with five, the fewest that can leave out a faulty point and
    still see every fault of the others; UWB with the cabin's four anchors and
    with a fifth above their centre.
    """
    cabin = load_project(ROOT / "projects" / "cabin")
    rows = [(method, method, with_method(cabin, method)) for method in FAULTS]
    rows.insert(
        1, ("total_station, 5 points", "total_station", with_method(cabin, "total_station", 5))
    )
    rows.insert(3, ("uwb, 5 anchors", "uwb", fifth_anchor(cabin)))
    return rows


def fifth_anchor(project):
    """The project with a fifth UWB anchor above the centre of the four (UWB frame)."""
    uwb = project.localization.uwb
    anchors = dict(uwb.anchors)
    anchors["A5"] = tuple(ANCHORS_5[4])
    loc = project.localization.model_copy(
        update={"uwb": uwb.model_copy(update={"anchors": anchors})}
    )
    return project.model_copy(update={"localization": loc})


def fault_table(n: int, console: Console, methods: set[str] | None = None) -> None:
    table = Table(
        title=f"Fault injection, {n} stations of the cabin per row (alpha = {ALPHA}, "
        "alert limit = tolerances.position)"
    )
    for name in (
        "method",
        "fault",
        "failed",
        "refused",
        "excluded (correct)",
        "silently wrong",
        "below MDB",
        "silently wrong above MDB",
        "median error mm",
    ):
        table.add_column(name, justify="left" if name in ("method", "fault") else "right")
    for label, method, project in projects():
        if methods is not None and method not in methods:
            continue
        for fault in FAULTS[method]:
            t0 = time.process_time()
            r = fault_study(project, method, fault, n, seed=1)
            failed = f"{r.failed}" + (
                f" ({100 * r.failed / r.injected:.1f} % false alarms)" if fault == "clean" else ""
            )
            table.add_row(
                label,
                fault,
                failed,
                str(r.raised),
                f"{r.excluded} ({r.correctly_excluded})",
                str(r.silently_wrong),
                str(r.below_mdb),
                str(r.silently_wrong_above_mdb),
                f"{1e3 * r.median_error_m:.1f}",
            )
            console.log(f"{label} {fault}: {time.process_time() - t0:.1f} CPU s")
    console.print(table)
    console.print(
        f"A correct pose lies outside its {100 * (1 - ELLIPSOID):.1f} % ellipsoid by chance: "
        f"about {n * ELLIPSOID:.1f} silently wrong per row are expected from the noise alone."
    )


def static_table(n_epochs: int, console: Console) -> None:
    sigma = 0.05
    table = Table(title=f"Static UWB, 5 anchors, {len(POINTS)} points x {n_epochs} epochs")
    for name in ("ranges", "LS mean mm", "WLS-T mean mm", "WLS-T + snooping mean mm", "gain"):
        table.add_column(name, justify="right")
    for nlos in (0.0, 0.02):
        model = dataclasses.replace(UwbErrorModel.gaussian(sigma), nlos_prob=nlos)
        err: dict[str, list[np.ndarray]] = {"ls": [], "wls-t": [], "fde": []}
        for k, p in enumerate(POINTS):
            sim = simulate_ranges(
                ANCHORS_5, np.broadcast_to(p, (n_epochs, 3)), model, np.random.default_rng(k)
            )
            for name, kw in (
                ("ls", {"method": "ls"}),
                ("wls-t", {"method": "wls-t"}),
                ("fde", {"method": "wls-t", "alpha": ALPHA}),
            ):
                fix = locate(ANCHORS_5, sim.ranges, sigma=sigma, **kw)
                err[name].append(np.linalg.norm(fix.positions - p, axis=1))
        mean = {k: float(np.nanmean(np.concatenate(v))) for k, v in err.items()}
        table.add_row(
            "clean" if nlos == 0 else f"{100 * nlos:.0f} % NLOS (+0.3..1.5 m)",
            f"{1e3 * mean['ls']:.1f}",
            f"{1e3 * mean['wls-t']:.1f}",
            f"{1e3 * mean['fde']:.1f}",
            f"{100 * (1 - mean['fde'] / mean['ls']):.0f} % over LS",
        )
        if nlos == 0:
            bound = np.sqrt(np.mean([np.trace(crlb(ANCHORS_5, p, sigma)) for p in POINTS]))
            rms = float(np.sqrt(np.nanmean(np.concatenate(err["fde"]) ** 2)))
            clean_ratio = rms / bound
    console.print(table)
    console.print(
        f"clean data: WLS-T with snooping RMS / CRLB = {clean_ratio:.3f} (target within 5 %)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few stations per row")
    parser.add_argument("--n", type=int, default=200, help="stations per method and fault")
    parser.add_argument("--methods", help=f"comma-separated, of {', '.join(FAULTS)} (default: all)")
    args = parser.parse_args()
    methods = None if args.methods is None else set(args.methods.split(","))
    if methods is not None and not methods <= set(FAULTS):
        parser.error(f"--methods: unknown {', '.join(sorted(methods - set(FAULTS)))}")
    console = Console(width=150)
    fault_table(8 if args.quick else args.n, console, methods)
    static_table(500 if args.quick else 5000, console)


if __name__ == "__main__":
    main()
