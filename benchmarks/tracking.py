"""Closed-loop print tracking on the simulated hydraulic excavator (paper 000, section IV).

Runs ``projects/excavator_print`` (a 1.6 m wall with round ends, two 5 cm
layers, 90 s at 0.1 m/s) closed loop (LiDAR ICP at 10 Hz with 0.1 s latency,
fused with 100 Hz kinematics by the EKF) and open loop (joint sensors only) for
N seeds (machine errors, sensor noise), and prints per figure the median and
the worst over the seeds beside paper 000's:

* tracking RMSE and max of the true nozzle against the reference, closed and
  open loop, and the improvement;
* estimation errors at 100 Hz of the fused estimate, the kinematics alone and
  the latest ICP fix (latency and hold included), and each ICP fix at its scan
  time (as the paper measured its ICP);
* the real-time factor: machine time simulated over the closed loop's wall time
  (shared 2-core machine: a median, the load average printed).

Then the same machine with a longer hydraulic dead time (0.16 s, 0.3 s): the
controller's margin.

Run: ``.venv/bin/python benchmarks/tracking.py [--quick] [--seeds N]``
(``--quick``: one seed on a one-layer print).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from fabflow.project import Project, load_project
from fabflow.tracking.report import PAPER_000, summary
from fabflow.tracking.run import track_print

ROOT = Path(__file__).resolve().parents[1]


def _project(quick: bool, **tracking: float) -> Project:
    p = load_project(ROOT / "projects" / "excavator_print")
    if quick:
        spec = p.elements[0].print_path.model_copy(update={"n_layers": 1})
        source = p.elements[0].model_copy(update={"print_path": spec})
        p = p.model_copy(update={"elements": [source]})
    if tracking:
        p = p.model_copy(update={"tracking": p.tracking.model_copy(update=tracking)})
    return p


def _figures(p: Project, seed: int) -> dict[str, float]:
    closed, open_ = track_print(p, "closed", seed), track_print(p, "open", seed)
    s = summary(closed, open_, p.tracking.icp_latency_s)
    t, e = s["tracking"], s["estimation"]
    return {
        "tracking closed loop RMSE": 100 * t["closed_loop"]["rmse_m"],
        "tracking closed loop max": 100 * t["closed_loop"]["max_m"],
        "tracking open loop RMSE": 100 * t["open_loop"]["rmse_m"],
        "tracking open loop max": 100 * t["open_loop"]["max_m"],
        "improvement (x)": t["improvement"],
        "fused estimate RMSE": 100 * e["fused"]["rmse_m"],
        "kinematics alone RMSE": 100 * e["kinematics"]["rmse_m"],
        "last ICP fix (held) RMSE": 100 * e["icp"]["rmse_m"],
        "ICP fix at its scan time RMSE": 100 * e["icp_at_scan"]["rmse_m"],
        "ICP fixes gated (%)": 100 * s["icp"]["gated"] / max(s["icp"]["fixes"], 1),
        "real-time factor (x)": s["speed"]["realtime_factor"],
    }


PAPER = {
    "tracking closed loop RMSE": 100 * PAPER_000["tracking_rmse_m"],
    "tracking closed loop max": 100 * PAPER_000["tracking_max_m"],
    "kinematics alone RMSE": 100 * PAPER_000["kinematics_rmse_m"],
    "ICP fix at its scan time RMSE": 100 * PAPER_000["icp_rmse_m"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one seed, one layer")
    ap.add_argument("--seeds", type=int, default=10, help="seeds (machines) to run")
    args = ap.parse_args()
    n = 1 if args.quick else args.seeds
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    p = _project(args.quick)
    rows = [_figures(p, seed) for seed in range(n)]
    print(f"\n1. {p.name}: {n} seed(s), closed vs open loop (cm unless stated)")
    print(f"{'figure':34s} {'median':>8s} {'worst':>8s} {'paper 000':>10s}")
    for key in rows[0]:
        v = np.array([r[key] for r in rows])
        worst = v.min() if key.endswith("(x)") else v.max()
        paper = f"{PAPER[key]:.2f}" if key in PAPER else ""
        print(f"{key:34s} {np.median(v):8.2f} {worst:8.2f} {paper:>10s}")
    print("\n2. a slower hydraulic response (seed 0): closed-loop tracking, cm")
    print(f"{'dead time s':>12s} {'RMSE':>8s} {'max':>8s} {'open RMSE':>10s}")
    for dead in (0.08,) if args.quick else (0.08, 0.16, 0.3):
        f = _figures(_project(args.quick, dead_time_s=dead), 0)
        print(
            f"{dead:12.2f} {f['tracking closed loop RMSE']:8.2f} "
            f"{f['tracking closed loop max']:8.2f} {f['tracking open loop RMSE']:10.2f}"
        )


if __name__ == "__main__":
    main()
