"""What ``fabflow track`` writes: tracking.csv, tracking.png and summary.json.

``summary.json`` holds, in metres (3-D nozzle position, print only):

* ``tracking``: ``closed_loop`` and ``open_loop`` ``{rmse_m, max_m}`` of the true
  nozzle against the reference at equal times, and ``improvement`` (open-loop
  RMSE over closed-loop RMSE);
* ``estimation`` (closed-loop run, 100 Hz, what the controller had at each
  instant): ``fused`` (the EKF), ``kinematics`` (joint sensors and GNSS alone),
  ``icp`` (the latest ICP fix available: its latency and the 10 Hz hold
  included) and ``icp_at_scan`` (each fix against the truth at its scan's time,
  as paper 000 measured its ICP);
* ``icp``: fixes made, failed, applied, gated and too old, and their mean NIS;
* ``speed``: the print's duration, the machine time simulated (the settling
  included), the loops' wall time and the real-time factor (machine time over
  the closed loop's wall time);
* ``paper``: paper 000's figures beside them.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from numpy.typing import NDArray

from fabflow.output import write_json
from fabflow.tracking.run import TrackingRun

FloatArray = NDArray[np.float64]

PAPER_000 = {
    "tracking_rmse_m": 0.009,
    "tracking_max_m": 0.038,
    "icp_rmse_m": 0.0058,
    "kinematics_rmse_m": 0.0223,
}
"""Paper 000's results: tracking RMSE and max (IV-C), ICP and kinematics RMSE (IV-A)."""

CSV_COLUMNS = (
    "t",
    "x_ref",
    "y_ref",
    "z_ref",
    "x_true",
    "y_true",
    "z_true",
    "x_est",
    "y_est",
    "z_est",
)


def error_stats(estimate: FloatArray, truth: FloatArray) -> dict[str, float]:
    """RMSE and max of the 3-D distance between two ``(N, 3)`` position series (metres).

    Rows where either is NaN (no ICP fix yet) are left out.
    """
    d = np.linalg.norm(np.asarray(estimate) - np.asarray(truth), axis=1)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return {"rmse_m": float("nan"), "max_m": float("nan")}
    return {"rmse_m": float(np.sqrt(np.mean(d**2))), "max_m": float(d.max())}


def summary(closed: TrackingRun, open_: TrackingRun, latency_s: float) -> dict[str, Any]:
    # NaN (no ICP fix at all) is written as null by write_json
    """The figures of a closed-loop and an open-loop print of the same machine (see module)."""
    c = error_stats(closed.p_true, closed.p_ref)
    o = error_stats(open_.p_true, open_.p_ref)
    duration = float(closed.t[-1] - closed.t[0]) if len(closed.t) > 1 else 0.0
    counts = closed.counts
    return {
        "tracking": {"closed_loop": c, "open_loop": o, "improvement": o["rmse_m"] / c["rmse_m"]},
        "estimation": {
            "fused": error_stats(closed.p_est, closed.p_true),
            "kinematics": error_stats(closed.p_kin, closed.p_true),
            "icp": error_stats(closed.p_icp, closed.p_true),
            "icp_at_scan": error_stats(closed.icp_error, np.zeros_like(closed.icp_error)),
        },
        "icp": {
            "fixes": counts.get("fixes", 0),
            "failed": counts.get("failed", 0),
            "applied": counts.get("icp_applied", 0),
            "gated": counts.get("icp_gated", 0),
            "too_old": counts.get("icp_too_old", 0),
            "mean_nis": closed.mean_nis if np.isfinite(closed.mean_nis) else None,
            "latency_s": latency_s,
        },
        "speed": {
            "print_s": duration,
            "simulated_s": closed.simulated_s,
            "closed_loop_wall_s": closed.wall_s,
            "open_loop_wall_s": open_.wall_s,
            "realtime_factor": closed.simulated_s / closed.wall_s if closed.wall_s > 0 else None,
        },
        "paper": PAPER_000,
    }


def write_csv(run: TrackingRun, path: Path) -> Path:
    """``tracking.csv``: time, reference, truth and fused estimate (metres, world frame)."""
    data = np.column_stack([run.t, run.p_ref, run.p_true, run.p_est])
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        w.writerows([f"{v:.6f}" for v in row] for row in data)
    return path


def plot(closed: TrackingRun, open_: TrackingRun, path: Path) -> Path:
    """``tracking.png``: the path in plan view, and the errors over time (cm)."""
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5), dpi=110)
    ax.plot(*closed.p_ref[:, :2].T, color="#228833", lw=2.5, label="reference")
    ax.plot(*open_.p_true[:, :2].T, color="#cc6677", lw=1, label="open loop (joint sensors)")
    ax.plot(*closed.p_true[:, :2].T, color="#4477aa", lw=1, label="closed loop (LiDAR + kin.)")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("print path, plan view")
    ax.legend(loc="best", fontsize=8)
    for run, p, label, colour in (
        (closed, closed.p_true, "tracking, closed loop", "#4477aa"),
        (open_, open_.p_true, "tracking, open loop", "#cc6677"),
        (closed, closed.p_est, "fused estimate error", "#999933"),
        (closed, closed.p_kin, "kinematics error", "#aa3377"),
    ):
        ref = run.p_ref if "tracking" in label else run.p_true
        bx.plot(run.t, 100 * np.linalg.norm(p - ref, axis=1), lw=0.8, label=label, color=colour)
    bx.set_xlabel("t (s)")
    bx.set_ylabel("error (cm)")
    bx.set_title("3-D nozzle error")
    bx.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def write_outputs(
    closed: TrackingRun, open_: TrackingRun, out: Path, meta: dict[str, Any]
) -> dict[str, Any]:
    """Write tracking.csv, tracking.png and summary.json into ``out``; return the summary."""
    data = {**meta, **summary(closed, open_, float(meta.get("icp_latency_s", 0.0)))}
    write_csv(closed, out / "tracking.csv")
    plot(closed, open_, out / "tracking.png")
    write_json(out / "summary.json", data)
    return data
