"""UWB positioning benchmark: the paper's tables (seeds/003, tables 1-7) on simulated sensors.

Prints
  1. static 3D (table 2 layout and points) with unbiased Gaussian noise: LS / WLS / WLS-T
     RMSE beside the Cramer-Rao bound;
  2. static 2D and 3D (tables 1, 2) with the full error model (the default white noise,
     per-anchor bias removed by a simulated calibration, 2 % NLOS outliers removed by the
     running median; no multipath): mean absolute error per axis, gain over LS, with and
     without outliers;
  3. moving (tables 3, 4, 5, 7): LS / WLS-T / CV-EKF / ESKF mean error per axis and XY,
     beside the paper's numbers;
  4. speed: batch fixes per second and ESKF steps per second (real-time factor);
  5. simulated station localization: error and consistency of the reported covariance.

Run: ``.venv/bin/python benchmarks/uwb.py [--quick] [--seed N] [--json PATH]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from fabflow.positioning.cv_ekf import cv_ekf_track
from fabflow.positioning.eskf import (
    Eskf,
    EskfParams,
    default_covariance,
    initial_attitude,
    run_eskf,
)
from fabflow.positioning.uwb import crlb, horizontal_ranges, locate
from fabflow.positioning.uwb_calibration import RangeCalibration, reject_outliers
from fabflow.sensors.imu import ImuErrorModel, simulate_imu
from fabflow.sensors.uwb import (
    PAPER_ANCHORS_2D,
    PAPER_ANCHORS_3D,
    PAPER_POINTS_2D,
    PAPER_POINTS_3D,
    UwbErrorModel,
    calibration_campaign,
    draw_bias,
    paper_trajectories,
    ranging_schedule,
    simulate_ranges,
)
from fabflow.sensors.uwb_trajectories import PlanarTrajectory

METHODS = ("ls", "wls", "wls-t")
# seeds/003 tables (cm): X, Y, Z mean absolute error and XOY projection error
PAPER_STATIC = {
    "2d": {"ls": (9.6, 7.5), "wls-t": (3.9, 2.7)},
    "3d": {"ls": (12.1, 12.2, 23.1), "wls-t": (6.7, 4.9, 11.7)},
}
PAPER_MOVING: dict[str, dict[str, tuple[float, ...]]] = {
    "rect2d H=2.10": {"ls": (7.8, 9.5), "wls-t": (6.3, 8.5), "eskf": (4.9, 6.8)},
    "rect2d H=2.20": {"ls": (9.5, 12.0), "wls-t": (6.8, 7.8), "eskf": (4.0, 5.8)},
    "rect2d H=2.30": {"ls": (7.2, 9.4), "wls-t": (6.2, 7.1), "eskf": (4.8, 5.1)},
    "line3d H=1.60": {
        "ls": (10.2, 10.1, 24.5, 14.8),
        "wls-t": (5.9, 7.4, 20.6, 9.9),
        "eskf": (4.6, 3.8, 14.2, 6.2),
    },
    "line3d H=2.00": {
        "ls": (9.1, 6.1, 24.3, 11.8),
        "wls-t": (5.5, 3.9, 23.5, 7.3),
        "eskf": (4.7, 2.9, 12.9, 5.5),
    },
    "line3d H=2.40": {
        "ls": (8.2, 4.6, 26.0, 10.0),
        "wls-t": (8.0, 2.7, 24.9, 8.7),
        "eskf": (6.8, 3.4, 11.7, 7.8),
    },
    "rect3d H=2.00": {
        "ls": (9.3, 8.3, 23.5, 13.7),
        "wls-t": (5.1, 5.4, 16.6, 7.6),
        "eskf": (4.1, 4.6, 14.5, 7.0),
    },
    "rect3d H=2.10": {
        "ls": (8.8, 10.8, 17.8, 15.6),
        "wls-t": (5.1, 9.1, 8.4, 11.7),
        "eskf": (5.4, 7.3, 7.1, 9.6),
    },
    "rect3d H=2.20": {
        "ls": (9.3, 8.4, 10.2, 13.2),
        "wls-t": (4.3, 5.8, 9.8, 7.9),
        "eskf": (4.1, 5.5, 9.5, 7.4),
    },
    "u H=2.00": {"ls": (8.7, 9.1, 16.1), "wls-t": (7.0, 6.7, 12.8), "eskf": (3.9, 5.2, 8.0)},
}


def cm(v: Any) -> str:
    return " ".join(f"{100 * x:5.1f}" for x in np.atleast_1d(v))


def pct(a: float, b: float) -> str:
    """Gain of ``b`` over ``a`` in percent, as an integer string (no "-0")."""
    return str(round(100 * (1 - b / a)) + 0)


# ------------------------------------------------------------------- static


def static_gaussian(rng: np.random.Generator, n: int) -> dict[str, Any]:
    sigma = 0.05
    model = UwbErrorModel.gaussian(sigma)
    print(f"\n1. Static 3D, table 2 layout, unbiased Gaussian noise sigma = {sigma} m, {n} epochs")
    print("   point (m)            RMSE 3D (cm): LS    WLS   WLS-T |  CRLB  | WLS-T/CRLB")
    sq = {m: [] for m in METHODS}
    bound_sq = []
    rows = []
    for p in PAPER_POINTS_3D:
        sim = simulate_ranges(PAPER_ANCHORS_3D, np.broadcast_to(p, (n, 3)), model, rng)
        rmse = {}
        for m in METHODS:
            fix = locate(PAPER_ANCHORS_3D, sim.ranges, method=m, sigma=sigma)
            e2 = np.sum((fix.positions[fix.valid] - p) ** 2, axis=1)
            sq[m].append(e2.mean())
            rmse[m] = math.sqrt(e2.mean())
        b = float(np.trace(crlb(PAPER_ANCHORS_3D, p, sigma)))
        bound_sq.append(b)
        rows.append({"point": p.tolist(), "rmse": rmse, "crlb": math.sqrt(b)})
        print(
            f"   ({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f})                {cm(rmse['ls'])} "
            f"{cm(rmse['wls'])} {cm(rmse['wls-t'])} | {cm(math.sqrt(b))}  | "
            f"{rmse['wls-t'] / math.sqrt(b):.3f}"
        )
    tot = {m: math.sqrt(np.mean(v)) for m, v in sq.items()}
    tb = math.sqrt(np.mean(bound_sq))
    print(
        f"   all points                       {cm(tot['ls'])} {cm(tot['wls'])} "
        f"{cm(tot['wls-t'])} | {cm(tb)}  | {tot['wls-t'] / tb:.3f}   (target <= 1.10)"
    )
    return {"points": rows, "rmse": tot, "crlb": tb, "ratio": tot["wls-t"] / tb}


def _static_run(
    rng: np.random.Generator,
    anchors: np.ndarray,
    points: np.ndarray,
    n: int,
    model: UwbErrorModel,
    tag_z: float | None,
) -> dict[str, Any]:
    """Per point: a dwell of n rounds; bias, calibration, median rejection, per-epoch fixes."""
    dim = 2 if tag_z is not None else 3
    errs = {m: [] for m in METHODS}
    dropped = 0
    total = 0
    bias = draw_bias(len(anchors), model, rng)
    cal = RangeCalibration.fit(*calibration_campaign(model, bias, rng))
    A_fix = anchors[:, :2] if tag_z is not None else anchors
    # mean |error| of an efficient unbiased per-fix estimator: sqrt(2 / pi) sqrt(CRLB_ii)
    bound = np.mean(
        [np.sqrt(2 / np.pi * np.diag(crlb(A_fix, p[:dim], model.sigma))) for p in points], axis=0
    )
    for p in points:
        p3 = np.array([*p, tag_z]) if tag_z is not None else p
        sim = simulate_ranges(anchors, np.broadcast_to(p3, (n, 3)), model, rng, bias=bias)
        y = cal.apply(sim.ranges)
        y = reject_outliers(y, model.sigma(y)).ranges  # standing: the white noise alone
        A = anchors
        if tag_z is not None:
            y = horizontal_ranges(y, anchors[:, 2], tag_z)
            A = anchors[:, :2]
        for m in METHODS:
            fix = locate(A, y, method=m, sigma=model.sigma)
            errs[m].append(np.abs(fix.positions[fix.valid] - p[:dim]))
            if m == "ls":
                dropped += int((~fix.valid).sum())
                total += n
    return {
        "mae": {m: np.concatenate(v).mean(axis=0) for m, v in errs.items()},
        "dropped": dropped / total,
        "crlb": bound,
    }


def static_full(rng: np.random.Generator, n: int) -> dict[str, Any]:
    model = UwbErrorModel()
    print(
        f"\n2. Static, full error model (sigma(d) = {model.sigma_1m} m + {model.growth} m/m, "
        f"per-anchor bias + calibration, {100 * model.nlos_prob:.0f} % NLOS "
        f"+{model.nlos_excess[0]}..{model.nlos_excess[1]} m, running-median rejection), "
        f"{n} epochs per point"
    )
    out: dict[str, Any] = {}
    for name, anchors, points, tag_z in (
        ("2d", PAPER_ANCHORS_2D, PAPER_POINTS_2D, 2.20),
        ("3d", PAPER_ANCHORS_3D, PAPER_POINTS_3D, None),
    ):
        seed = int(rng.integers(2**31))
        clean = _static_run(
            np.random.default_rng(seed), anchors, points, n, model.without_outliers(), tag_z
        )
        full = _static_run(np.random.default_rng(seed), anchors, points, n, model, tag_z)
        axes = "X / Y" if tag_z is not None else "X / Y / Z"
        print(f"   {name.upper()} (table {1 if tag_z else 2}) mean abs error {axes} (cm)")
        print(
            "   method   outlier-free         with outliers        gain over LS   paper"
            "          paper gain"
        )
        for m in METHODS:
            c, f = clean["mae"][m], full["mae"][m]
            pg = ""
            paper = PAPER_STATIC[name].get(m)
            if paper is not None:
                pl = PAPER_STATIC[name]["ls"]
                pg = " / ".join(pct(a, b) for a, b in zip(pl, paper, strict=True)) + " %"
            g = " / ".join(pct(a, b) for a, b in zip(full["mae"]["ls"], f, strict=True))
            print(
                f"   {m:6s}  {cm(c):20s} {cm(f):20s} {g + ' %':14s} "
                f"{' '.join(f'{v:5.1f}' for v in paper) if paper else '':14s} {pg}"
            )
        print(
            f"   CRLB    {cm(clean['crlb']):20s} (mean |error| of an efficient per-fix estimator)"
        )
        mean_clean = float(np.mean(clean["mae"]["wls-t"]))
        mean_full = float(np.mean(full["mae"]["wls-t"]))
        overall_gain = 1 - np.sum(full["mae"]["wls-t"]) / np.sum(full["mae"]["ls"])
        print(
            f"   WLS-T with/without outliers: {mean_full / mean_clean:.2f} (target <= 1.5); "
            f"overall gain over LS {100 * overall_gain:.0f} % (paper 53 %); "
            f"epochs dropped (a range rejected, too few left): {100 * full['dropped']:.1f} %"
        )
        out[name] = {
            "clean": {k: v.tolist() for k, v in clean["mae"].items()},
            "full": {k: v.tolist() for k, v in full["mae"].items()},
            "outlier_ratio": mean_full / mean_clean,
            "gain_over_ls": float(overall_gain),
            "dropped": full["dropped"],
            "crlb": clean["crlb"].tolist(),
        }
    return out


# ------------------------------------------------------------------- moving


def run_moving(
    rng: np.random.Generator,
    traj: PlanarTrajectory,
    anchors: np.ndarray,
    two_d: bool,
    with_cv: bool,
    model: UwbErrorModel | None = None,
    ls_raw: bool = False,
) -> tuple[dict[str, np.ndarray], float]:
    """One moving run: mean abs error per axis and XOY of each estimator, and ESKF steps
    per second. ``ls_raw``: LS reads the ranges uncalibrated (the paper's baseline, see
    ``benchmarks/sensor_models.py``), the others calibrated."""
    model = model or UwbErrorModel()
    bias = draw_bias(4, model, rng)
    cal = RangeCalibration.fit(*calibration_campaign(model, bias, rng))
    t, _, ai = ranging_schedule(traj.duration, 60.0, 4)
    t, ai = t[:, 0, :], ai[:, 0, :]
    truth = traj.sample(t.ravel()).p.reshape(*t.shape, 3)
    sim = simulate_ranges(anchors, truth, model, rng, bias=bias, dt=1.0 / 60.0)
    raw = np.einsum("rjj->rj", sim.ranges)
    y = cal.apply(raw)
    y_rej = reject_outliers(y, model.total_sigma(y)).ranges
    t_round = t.mean(axis=1)
    p_round = traj.sample(t_round).p
    warm = t_round > 1.0
    res: dict[str, np.ndarray] = {}
    dim = 2 if two_d else 3
    A = anchors[:, :2] if two_d else anchors
    # per-fix bound: per-axis sqrt(2 / pi) sqrt(C_ii); XOY by sampling N(0, C_xy)
    C = crlb(A, p_round[warm][:, :dim], model.total_sigma)
    draws = np.einsum(
        "nij,nkj->nki", np.linalg.cholesky(C[:, :2, :2]), rng.standard_normal((len(C), 16, 2))
    )
    res["crlb"] = np.r_[
        np.sqrt(2 / np.pi * np.diagonal(C, axis1=1, axis2=2)).mean(axis=0),
        np.linalg.norm(draws, axis=-1).mean(),
    ]
    yy = horizontal_ranges(y_rej, anchors[:, 2], traj.z) if two_d else y_rej
    for m in ("ls", "wls-t"):
        if m == "ls" and ls_raw:
            y_m = reject_outliers(raw, model.total_sigma(raw)).ranges
            y_m = horizontal_ranges(y_m, anchors[:, 2], traj.z) if two_d else y_m
        else:
            y_m = yy
        fix = locate(A, y_m, method=m, sigma=model.total_sigma)
        ok = fix.valid & warm
        e = np.abs(fix.positions[ok] - p_round[ok][:, :dim])
        res[m] = np.r_[e.mean(axis=0), np.linalg.norm(e[:, :2], axis=1).mean()]
    start = locate(A, yy[:60], method="wls-t", sigma=model.total_sigma)
    p0 = np.nanmedian(start.positions, axis=0)
    if two_d:
        p0 = np.r_[p0, traj.z]
    if with_cv:
        tc, pc, _ = cv_ekf_track(
            t.ravel(), ai.ravel(), y.ravel(), anchors, model.total_sigma, p0=p0
        )
        ok = tc > 1.0
        e = np.abs(pc[ok] - traj.sample(tc[ok]).p)[:, :dim]
        res["cv-ekf"] = np.r_[e.mean(axis=0), np.linalg.norm(e[:, :2], axis=1).mean()]
    imu = simulate_imu(traj, 100.0, ImuErrorModel(), rng)
    yaw0 = traj.sample(np.zeros(1)).yaw[0] + math.radians(5.0) * rng.standard_normal()
    rest = imu.t < 1.0
    filt = Eskf(
        p0, np.zeros(3), initial_attitude(imu.accel[rest], yaw0), default_covariance(), EskfParams()
    )
    tic = time.perf_counter()
    track = run_eskf(
        filt,
        imu.t,
        imu.accel,
        imu.gyro,
        t.ravel(),
        ai.ravel(),
        y.ravel(),
        anchors,
        model.total_sigma,
        height=(traj.z, 0.01) if two_d else None,
    )
    elapsed = time.perf_counter() - tic
    ok = imu.t > 1.0
    e = np.abs(track.p[ok] - traj.sample(imu.t[ok]).p)[:, :dim]
    res["eskf"] = np.r_[e.mean(axis=0), np.linalg.norm(e[:, :2], axis=1).mean()]
    return res, imu.t.size / elapsed


def moving(rng: np.random.Generator, quick: bool) -> dict[str, Any]:
    trajs = paper_trajectories()
    groups = [
        ("rect2d", PAPER_ANCHORS_2D, True, "table 3"),
        ("line3d", PAPER_ANCHORS_3D, False, "table 4"),
        ("rect3d", PAPER_ANCHORS_3D, False, "table 5"),
        ("u", PAPER_ANCHORS_2D, True, "table 7"),
    ]
    print(
        "\n3. Moving (0.3 m/s, cosine ramps, 3 s rests), full error model; LS / WLS-T / CV-EKF get "
        "\n   calibrated + median-rejected ranges, CV-EKF and ESKF get calibrated ranges and gate "
        "\n   them (99.7 %). Mean abs error X / Y [/ Z] and XOY-PE (cm); paper in brackets."
        "\n   crlb = what an efficient single-fix estimator reaches (filters can go below it)."
    )
    out: dict[str, Any] = {}
    pe: dict[str, list[float]] = {m: [] for m in ("crlb", "ls", "wls-t", "cv-ekf", "eskf")}
    speeds = []
    for name, anchors, two_d, table in groups:
        items = trajs[name][:1] if quick else trajs[name]
        for traj in items:
            res, steps_per_s = run_moving(rng, traj, anchors, two_d, with_cv=not quick)
            speeds.append(steps_per_s)
            paper = PAPER_MOVING.get(traj.name, {})
            print(
                f"   {traj.name} ({table}, {'2D layout + known height' if two_d else '3D layout'})"
            )
            for m, v in res.items():
                pv = paper.get(m)
                ps = f"[{' '.join(f'{x:5.1f}' for x in pv)}]" if pv else ""
                print(f"     {m:7s} {cm(v):28s} {ps}")
                pe[m].append(v[-1])
            out[traj.name] = {m: v.tolist() for m, v in res.items()}
    means = {m: float(np.mean(v)) for m, v in pe.items() if v}
    print(
        "   mean XOY-PE over all runs (cm): "
        + ", ".join(f"{m} {100 * v:.1f}" for m, v in means.items())
    )
    print(
        f"   ESKF gain over LS: {100 * (1 - means['eskf'] / means['ls']):.0f} % (target >= 40 %, "
        f"paper 46 %); over WLS-T: {100 * (1 - means['eskf'] / means['wls-t']):.0f} % (paper 25 %)"
    )
    out["mean_pe"] = means
    out["eskf_steps_per_s_in_runs"] = float(np.median(speeds))

    mp = dataclasses.replace(UwbErrorModel(), multipath_sigma=0.03, multipath_tau=1.0)
    print(
        "\n3b. Sensitivity (not in the paper's error model): the same plus time-correlated "
        f"multipath\n    per link (Gauss-Markov, sigma {100 * mp.multipath_sigma:.0f} cm, "
        f"tau {mp.multipath_tau:.0f} s), which no filter can average away. XOY-PE (cm):"
    )
    sens = {}
    cases = [("rect3d", PAPER_ANCHORS_3D, False), ("u", PAPER_ANCHORS_2D, True)]
    for name, anchors, two_d in cases[1:] if quick else cases:
        traj = trajs[name][0]
        res, _ = run_moving(rng, traj, anchors, two_d, with_cv=False, model=mp)
        pes = {m: float(v[-1]) for m, v in res.items()}
        sens[traj.name] = pes
        print(
            f"    {traj.name:14s} "
            + ", ".join(f"{m} {100 * v:.1f}" for m, v in pes.items())
            + f"; ESKF gain over LS {100 * (1 - pes['eskf'] / pes['ls']):.0f} %"
        )
    out["multipath_sensitivity"] = sens
    return out


# -------------------------------------------------------------------- speed


def speed(rng: np.random.Generator, quick: bool) -> dict[str, Any]:
    n = 20_000 if quick else 100_000
    reps = 3 if quick else 5
    sim = simulate_ranges(
        PAPER_ANCHORS_3D, np.broadcast_to(PAPER_POINTS_3D[0], (n, 3)), UwbErrorModel(), rng
    )
    print(f"\n4. Speed (this machine, {n} epochs x 4 anchors, median of {reps})")
    print("   (CPU time of this process; wall-clock in brackets, inflated on a shared machine)")
    out: dict[str, Any] = {}
    for m in METHODS:
        cpu, wall = [], []
        for _ in range(reps):
            c, w = time.process_time(), time.perf_counter()
            locate(PAPER_ANCHORS_3D, sim.ranges, method=m, sigma=0.05)
            cpu.append(time.process_time() - c)
            wall.append(time.perf_counter() - w)
        out[m] = n / float(np.median(cpu))
        out[m + "_wall"] = n / float(np.median(wall))
        target = "   (target >= 100,000)" if m == "wls-t" else ""
        print(f"   {m:6s} {out[m]:12,.0f} fixes/s  [{out[m + '_wall']:,.0f}]{target}")
    traj = paper_trajectories()["line3d"][0]
    dur = 8.0 if quick else traj.duration
    t, _, ai = ranging_schedule(dur, 60.0, 4)
    t, ai = t[:, 0, :], ai[:, 0, :]
    truth = traj.sample(t.ravel()).p.reshape(*t.shape, 3)
    y = np.einsum("rjj->rj", simulate_ranges(PAPER_ANCHORS_3D, truth, UwbErrorModel(), rng).ranges)
    imu = simulate_imu(traj, 100.0, ImuErrorModel(), rng, duration=dur)
    cpu, wall = [], []
    for _ in range(reps):
        filt = Eskf(
            truth[0, 0], np.zeros(3), initial_attitude(imu.accel[:50], 0.9), default_covariance()
        )
        c, w = time.process_time(), time.perf_counter()
        run_eskf(
            filt,
            imu.t,
            imu.accel,
            imu.gyro,
            t.ravel(),
            ai.ravel(),
            y.ravel(),
            PAPER_ANCHORS_3D,
            0.06,
        )
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    steps = imu.t.size / float(np.median(cpu))
    steps_wall = imu.t.size / float(np.median(wall))
    out["eskf_steps_per_s"] = steps
    out["eskf_realtime_factor"] = steps / 100.0
    out["eskf_realtime_factor_wall"] = steps_wall / 100.0
    print(
        f"   ESKF   {steps:12,.0f} IMU steps/s (+ 240 ranges/s of data) = {steps / 100:.0f}x "
        f"real time at 100 Hz [{steps_wall / 100:.0f}x] (target >= 50x)"
    )
    load = Path("/proc/loadavg")
    if load.exists():
        print(f"   load average during the run: {load.read_text().split()[0]} (2 cores shared)")
    return out


# ------------------------------------------------------------------ station


def stations(rng: np.random.Generator, n: int) -> dict[str, Any]:
    from fabflow.design.cabin import cabin_elements
    from fabflow.localize.uwb import localize_station
    from fabflow.project import load_project

    project = load_project(Path(__file__).resolve().parents[1] / "projects" / "cabin")
    spec = project.elements[0].cabin
    assert spec is not None
    blocks = cabin_elements(spec)
    print(
        f"\n5. Station localization (localize_station, cabin project, {n} random stations, "
        "2 tags, 5 s)\n   built blocks   RMS error x / y / z (mm), heading (deg)   "
        "RMS(error / reported sigma)"
    )
    out = {}
    for label, built in (("none", []), (f"all {len(blocks)}", blocks)):
        z, err = [], []
        for _ in range(n):
            yaw = rng.uniform(-np.pi, np.pi)
            T = np.eye(4)
            T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
            T[:3, 3] = [rng.uniform(-1.5, 5.5), rng.uniform(-1.5, 5.5), 1.0]
            pose = localize_station(project, T, rng, "S", built=built)
            Te = pose.T_world_base
            dyaw = np.angle(np.exp(1j * (np.arctan2(Te[1, 0], Te[0, 0]) - yaw)))
            e = np.r_[Te[:3, 3] - T[:3, 3], dyaw]
            z.append(e / np.sqrt(np.diag(pose.covariance))[[0, 1, 2, 5]])
            err.append(e)
        rms = np.sqrt(np.mean(np.square(err), axis=0)) * [1e3, 1e3, 1e3, 180 / np.pi]
        nz = np.sqrt(np.mean(np.square(z), axis=0))
        print(
            f"   {label:12s}   {rms[0]:.1f} / {rms[1]:.1f} / {rms[2]:.1f}, {rms[3]:.2f}"
            f"                 {' / '.join(f'{v:.2f}' for v in nz)}"
        )
        out[label] = {"rms_error": rms.tolist(), "rms_normalized": nz.tolist()}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small version (< ~20 s)")
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--json", type=Path, default=None, help="also write the figures as JSON")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    results = {
        "static_gaussian": static_gaussian(rng, 2000 if args.quick else 20000),
        "static_full": static_full(rng, 300 if args.quick else 3000),
        "moving": moving(rng, args.quick),
        "speed": speed(rng, args.quick),
        "stations": stations(rng, 8 if args.quick else 60),
    }
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2, default=float) + "\n")


if __name__ == "__main__":
    main()
