"""ICP covariance benchmark: does the predicted sigma match the real error?

For seeded simulated stations of a project (the parking poses of ``fabflow simulate``:
run ``i`` draws from ``SeedSequence(seed, spawn_key=(i,))``), the LiDAR scan of each
station is localized by :func:`fabflow.localize.icp.localize_station` and the base pose
error (true minus estimate, fabflow's convention) is compared with the predicted
covariance. Prints, per axis, the RMS error, the RMS predicted sigma and their ratio
(1: honest, above 1: over-confident, below 1: pessimistic), and how many results passed
their integrity checks.

Projects: ``tests/data/sim`` (one station at the origin of the simulated site; 120
stations) and ``projects/cabin`` (three stations inside the growing cabin, the blocks
built so far added to the map; 60 stations). ``--quick`` runs 8 stations of the first.

Run: ``.venv/bin/python benchmarks/icp_covariance.py [--quick] [--seed N]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from fabflow.localize.icp import localize_station
from fabflow.localize.methods import localizer_arguments
from fabflow.localize.plan import parked_pose
from fabflow.positioning.scan_matching import COVARIANCE_BLOCK
from fabflow.project import load_project
from fabflow.sim.run import prepare_study, run_seed
from fabflow.transforms.se3 import pose_error

ROOT = Path(__file__).resolve().parents[1]
AXES = ("x", "y", "z", "roll", "pitch", "heading")


def measure(folder: Path, n: int, seed: int) -> dict[str, object]:
    """Localize ``n`` seeded stations of a project; errors, sigmas and statuses."""
    project = load_project(folder)
    study = prepare_study(project, "icp")
    errors, sigmas, statuses = [], [], []
    run = 0
    t0 = time.perf_counter()
    while len(errors) < n:
        rng = np.random.default_rng(run_seed(seed, run))
        for v, station in enumerate(study.stations):
            if len(errors) >= n:
                break
            _, T_true = parked_pose(project, station, rng)
            pose = localize_station(
                project,
                T_true,
                rng,
                station.id,
                built=study.built_before[v],
                **localizer_arguments(project, "icp", station),
            )
            errors.append(pose_error(pose.T_world_base, T_true))
            sigmas.append(np.sqrt(np.clip(np.diag(pose.covariance), 0.0, None)))
            statuses.append("untested" if pose.integrity is None else pose.integrity.status)
        run += 1
    return {
        "errors": np.array(errors),
        "sigmas": np.array(sigmas),
        "statuses": statuses,
        "seconds": (time.perf_counter() - t0) / n,
    }


def report(name: str, m: dict[str, object]) -> None:
    """Print the per-axis table of one project."""
    e = np.asarray(m["errors"])
    s = np.asarray(m["sigmas"])
    statuses = list(m["statuses"])  # type: ignore[call-overload]
    rms = np.sqrt(np.mean(e**2, axis=0))
    sig = np.sqrt(np.mean(s**2, axis=0))
    counts = ", ".join(f"{k} {statuses.count(k)}" for k in sorted(set(statuses)))
    print(f"{name}: {len(e)} stations, {1e3 * float(m['seconds']):.0f} ms each; {counts}")
    print(f"{'axis':>8}  {'rms error':>12}  {'rms sigma':>12}  {'ratio':>6}")
    for k, axis in enumerate(AXES):
        unit, f = ("mm", 1e3) if k < 3 else ("mdeg", 1e3 * 180 / np.pi)
        print(
            f"{axis:>8}  {f * rms[k]:8.3f} {unit:<4}  {f * sig[k]:8.3f} {unit:<4}"
            f"  {rms[k] / sig[k]:6.2f}"
        )
    xy = np.sqrt(np.mean([(rms[k] / sig[k]) ** 2 for k in (0, 1)]))
    print(f"sigma ratio xy (as fabflow simulate prints it): {xy:.2f}\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="8 stations of tests/data/sim only")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(f"ICP covariance: blocked sandwich, {COVARIANCE_BLOCK:g} m blocks\n")
    cases = (
        [("tests/data/sim", 8)] if args.quick else [("tests/data/sim", 120), ("projects/cabin", 60)]
    )
    for folder, n in cases:
        report(folder, measure(ROOT / folder, n, args.seed))
    print("target: ratio within 0.8-1.25 in x, y and heading")


if __name__ == "__main__":
    main()
