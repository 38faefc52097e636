"""Sensor models against the papers' real-machine tables: fit on some, check on the others.

UWB (paper 003). The simulator's range error is the white, distance-dependent
noise, a per-anchor linear bias removed by the simulated calibration, NLOS
outliers and, new, the position-dependent multipath of
``fabflow.sensors.uwb_multipath`` (an error that stays while the tag stays and
changes over ``multipath_field_length`` as it moves). Its one free parameter,
the multipath's standard deviation, is fitted on the paper's **static** tables
(1, 2 and 6: the error of each point's fix averaged over 30 or 200 epochs, so
white noise has averaged away and what remains is what stays); with no further
change the **moving** tables (3, 4, 5 and 7) are then simulated as held-out
checks (LS, WLS-T and the UWB/IMU ESKF, per axis and the XOY projection). The
white noise is not fitted (the static tables average it away): it is the
DW1000's stated precision, 3.3 cm (``UwbErrorModel``). The estimators weight
each range by the white noise and the multipath together
(``UwbErrorModel.total_sigma``).

The paper's LS is read as its baseline on the ranges as the sensor gives them,
and WLS-T and the ESKF as getting them calibrated (section 3.3.1, the "improved"
pipeline of its figure 3). The paper does not say so in as many words; it is
the reading that reproduces its static tables, where LS errs 2.2 times as much
as WLS-T: fed the same calibrated ranges, LS errs about as much as WLS-T under
every range error model tried here (1.1 times), while the per-anchor offsets
the calibration removes (5-25 cm, the model's default, not fitted) give LS the
paper's static errors on their own.

LiDAR ICP (paper 000; scenarios in ``_lidar_paper000.py``). The range error is
the white noise (1 cm), the incidence-angle spread of a 3 mrad beam, and a
per-channel range bias drawn per run; the map is built by a simulated mapping
run that registers its scans one after the other, so it drifts. The one free
parameter, the channel bias's standard deviation, is fitted on section IV-A
(the moving end-effector's ICP RMSE against the total station, 0.58 cm: the
construction machine the simulator stands for, and the figure issue 20 asks
for); table I (a stationary sensor outdoors, runs at other times of day: the
deviation of the runs' positions) is the held-out check. It cannot fit both:
the paper's static outdoor spread (0.35-0.47 cm per axis) exceeds its moving
RMSE (0.58 cm in 3D), which the paper puts down to the sunlight and the
features' distance there; fitted on table I (3.5 cm) the moving RMSE came out at
2.1 times the paper's.

Kinematics only (paper 000, section IV-A's baseline: RMSE 2.23 cm): the
excavator that ``fabflow track`` simulates, with its error model
(``fabflow.sensors.excavator.ExcavatorErrors``), measures its tool by its joint
sensors, its GNSS base and its calibrated arm. The one free parameter, the RTK
GNSS error (the horizontal sigma; the vertical one keeps its ratio), is fitted
on that RMSE; the same run's largest error and its share within 1 cm are the
held-out checks.

Last, UWB through the built cabin: the wood's delay (``material_delay``) taken
off as the design predicts, and left on; and the UWB global test at the
cabin's visit with the most blocked lines of sight, against the same station
with nothing built (its p-values should be uniform: 10 % below 0.1).

Prints per table, estimator and axis the paper's value, the simulated one and
their ratio, then the mean ratio per role; ``--json FILE`` writes the rows
``{paper, table, estimator, axis, paper_value_m, simulated_value_m, role}``
(``role``: ``fit`` or ``holdout``; table I's orientation rows carry
``"unit": "deg"`` and degrees in the value fields).

    python benchmarks/sensor_models.py [--quick] [--seed N] [--json FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
from _lidar_paper000 import (
    ICP_RMSE_CM,
    KINEMATICS_MAX_CM,
    KINEMATICS_RMSE_CM,
    KINEMATICS_WITHIN_1CM,
    TABLE_I_OUTDOOR_CM,
    TABLE_I_OUTDOOR_DEG,
    kinematics_errors,
    moving_rmse,
    static_deviation,
)
from uwb import PAPER_MOVING, run_moving

from fabflow.design.generate import generate_elements
from fabflow.localize import uwb as uwb_station
from fabflow.localize.plan import parked_pose
from fabflow.localize.uwb import estimate_station as estimate_uwb_station
from fabflow.localize.uwb import simulate_station as simulate_uwb_station
from fabflow.positioning.uwb import horizontal_ranges, locate
from fabflow.positioning.uwb_calibration import RangeCalibration, reject_outliers
from fabflow.project import load_project
from fabflow.sensors.excavator import ExcavatorErrors
from fabflow.sensors.lidar_errors import LidarErrorModel
from fabflow.sensors.uwb import (
    PAPER_ANCHORS_2D,
    PAPER_ANCHORS_3D,
    PAPER_POINTS_2D,
    PAPER_POINTS_3D,
    UwbErrorModel,
    calibration_campaign,
    draw_bias,
    paper_trajectories,
    simulate_ranges,
)
from fabflow.sim.run import prepare_study
from fabflow.tasks.planner import make_plan
from fabflow.transforms.se3 import pose_error

ROOT = Path(__file__).resolve().parents[1]
TABLE6_POINTS = np.array(
    [[3.00, 5.05], [2.60, 2.30], [4.00, 4.90], [2.21, 0.60], [3.60, 0.35], [2.07, 5.25]]
)
"""Table 6 test points (the paper's site; its layout is not given: the 6.6 x 7.0 m
layout of table 1 is assumed, tag at the anchors' 2.20 m)."""

STATIC_TABLES = {
    # table: (anchors, points, tag height or None for 3D, epochs per point, paper cm)
    "1": (PAPER_ANCHORS_2D, PAPER_POINTS_2D, 2.20, 30, {"ls": (9.6, 7.5), "wls-t": (3.9, 2.7)}),
    "2": (
        PAPER_ANCHORS_3D,
        PAPER_POINTS_3D,
        None,
        30,
        {"ls": (12.1, 12.2, 23.1), "wls-t": (6.7, 4.9, 11.7)},
    ),
    "6": (PAPER_ANCHORS_2D, TABLE6_POINTS, 2.20, 200, {"ls": (5.3, 6.9), "wls-t": (2.4, 3.6)}),
}
MOVING_TABLES = {"rect2d": "3", "line3d": "4", "rect3d": "5", "u": "7"}
TWO_D = {"rect2d": True, "line3d": False, "rect3d": False, "u": True}
FIT_SIGMAS = (0.0, 0.01, 0.02, 0.025, 0.03, 0.035, 0.04, 0.05, 0.06, 0.08)
"""Candidate multipath standard deviations (metres) of the fit."""
LIDAR_BIAS_SIGMAS = (0.0, 0.005, 0.01, 0.015, 0.02, 0.025, 0.03)
"""Candidate channel range bias standard deviations (metres) of the LiDAR fit."""
GNSS_SIGMAS = (0.005, 0.0075, 0.01, 0.0125, 0.015)
"""Candidate horizontal GNSS standard deviations (metres) of the kinematics fit; the
vertical one keeps the error model's default ratio to it."""
WOOD_DELAY = 0.41
"""``sqrt(eps_r) - 1`` of wood of relative permittivity 2 (the UWB structure table)."""
LIDAR_FIXED = LidarErrorModel(beam_divergence=0.003, max_incidence_deg=85.0)
"""The LiDAR terms that are not fitted (a beam divergence common to spinning LiDARs)."""


def static_errors(
    model: UwbErrorModel,
    table: str,
    installations: int,
    rng: np.random.Generator,
    ls_raw: bool = True,
) -> dict[str, np.ndarray]:
    """Mean absolute error per axis of each point's averaged fix, as the paper's static
    tables report it, averaged over ``installations`` drawn installations. ``ls_raw``:
    LS reads the ranges uncalibrated (the module docstring)."""
    anchors, points, tag_z, epochs, _ = STATIC_TABLES[table]
    dim = 2 if tag_z is not None else 3
    A = anchors[:, :2] if tag_z is not None else anchors
    tags = np.c_[points, np.full(len(points), tag_z)] if tag_z is not None else points
    out: dict[str, list[np.ndarray]] = {"ls": [], "wls-t": []}
    for _ in range(installations):
        bias = draw_bias(len(anchors), model, rng)
        cal = RangeCalibration.fit(*calibration_campaign(model, bias, rng))
        truth = np.broadcast_to(tags[:, None, :], (len(tags), epochs, 3))
        sim = simulate_ranges(anchors, truth, model, rng, bias=bias)
        for method in out:
            errors = []
            for k in range(len(tags)):
                # the paper's LS is its baseline on the ranges as measured (module docstring)
                y = sim.ranges[k] if method == "ls" and ls_raw else cal.apply(sim.ranges[k])
                # a standing tag: its multipath stays, so the epochs scatter by the white
                # noise alone (the cleaning and weights of fabflow.localize.uwb_static)
                y = reject_outliers(y, model.sigma(y)).ranges
                if tag_z is not None:
                    y = horizontal_ranges(y, anchors[:, 2], tag_z)
                fix = locate(A, y, method=method, sigma=model.sigma)
                mean = np.nanmean(fix.positions[fix.valid], axis=0)
                errors.append(np.abs(mean - tags[k, :dim]))
            out[method].append(np.mean(errors, axis=0))
    return {m: np.mean(v, axis=0) for m, v in out.items()}


def _log_misfit(rows: list[dict]) -> float:
    ratios = np.array([r["simulated_value_m"] / r["paper_value_m"] for r in rows])
    return float(np.mean(np.log(ratios) ** 2))


def static_rows(model: UwbErrorModel, installations: int, seed: int) -> list[dict]:
    rows = []
    for table, (*_, paper) in STATIC_TABLES.items():
        sim = static_errors(model, table, installations, np.random.default_rng(seed))
        for method, values in paper.items():
            for axis, (p, s) in enumerate(zip(values, sim[method], strict=False)):
                rows.append(_row(table, method, "XYZ"[axis], p, s, "fit"))
    return rows


def moving_rows(model: UwbErrorModel, runs: int, seed: int, quick: bool) -> list[dict]:
    rows = []
    rng = np.random.default_rng(seed)
    trajectories = paper_trajectories()
    for group, table in MOVING_TABLES.items():
        anchors = PAPER_ANCHORS_2D if TWO_D[group] else PAPER_ANCHORS_3D
        for traj in trajectories[group][:1] if quick else trajectories[group]:
            results = [
                run_moving(rng, traj, anchors, TWO_D[group], False, model, ls_raw=True)[0]
                for _ in range(runs)
            ]
            paper = PAPER_MOVING[traj.name]
            for method in ("ls", "wls-t", "eskf"):
                sim = np.mean([r[method] for r in results], axis=0)
                axes = ["X", "Y", "XOY"] if TWO_D[group] else ["X", "Y", "Z", "XOY"]
                n = len(paper[method])  # table 3 gives X and Y only
                for axis, p, s in zip(axes[:n], paper[method], sim[:n], strict=True):
                    rows.append(_row(f"{table} {traj.name}", method, axis, p, s, "holdout"))
    return rows


def lidar_static_rows(errors: LidarErrorModel, runs: int, seed: int) -> list[dict]:
    """Table I (outdoor): position rows (metres) and orientation rows (stored in degrees
    as the paper gives them, in the value fields)."""
    pos, ang, _ = static_deviation(errors, runs, seed)
    rows = [
        _row("I outdoor", "icp", axis, TABLE_I_OUTDOOR_CM[axis], v, "holdout", paper="000")
        for axis, v in zip("xyz", pos, strict=True)
    ]
    rows += [
        _row("I outdoor", "icp", axis, 100 * p, v, "holdout", paper="000", unit="deg")
        for (axis, p), v in zip(TABLE_I_OUTDOOR_DEG.items(), ang, strict=True)
    ]
    return rows


def _row(
    table: str,
    method: str,
    axis: str,
    paper_cm: float,
    sim_m: float,
    role: str,
    paper: str = "003",
    unit: str = "m",
) -> dict:
    """One row; ``unit="deg"`` (an angle) stores degrees where the metres go, and says so."""
    row = {
        "paper": paper,
        "table": table,
        "estimator": method,
        "axis": axis,
        "paper_value_m": round(paper_cm / 100.0, 4),
        "simulated_value_m": round(float(sim_m), 5),
        "role": role,
    }
    if unit != "m":
        row["unit"] = unit
    return row


def _print(rows: list[dict], title: str) -> None:
    print(f"\n{title}")
    print(
        f"   {'table':<20} {'estimator':<7} {'axis':<5} {'paper':>8} {'sim':>8} {'unit':<4} "
        f"{'ratio':>6}"
    )
    for r in rows:
        ratio = r["simulated_value_m"] / r["paper_value_m"]
        unit, scale = ("cm", 100.0) if r.get("unit", "m") == "m" else (r["unit"], 1.0)
        print(
            f"   {r['table']:<20} {r['estimator']:<7} {r['axis']:<5} "
            f"{scale * r['paper_value_m']:>8.2f} {scale * r['simulated_value_m']:>8.2f} "
            f"{unit:<4} {ratio:>6.2f}"
        )


def _summary(rows: list[dict]) -> str:
    parts = []
    for method in ("ls", "wls-t", "eskf"):
        r = [x["simulated_value_m"] / x["paper_value_m"] for x in rows if x["estimator"] == method]
        if r:
            parts.append(f"{method} {np.mean(r):.2f} ({min(r):.2f}-{max(r):.2f})")
    return ", ".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer installations and runs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="write the rows as JSON")
    parser.add_argument(
        "--length", type=float, default=UwbErrorModel().multipath_field_length,
        help="the multipath's correlation length (m; a sensitivity, not fitted)",
    )  # fmt: skip
    parser.add_argument("--sigma", type=float, help="skip the fit: this multipath sigma (m)")
    args = parser.parse_args()
    installations = 8 if args.quick else 24
    base = dataclasses.replace(UwbErrorModel(), multipath_field_length=args.length)
    print(
        "UWB, paper 003. Fit: the multipath standard deviation on the static tables "
        f"(mean over {installations} simulated installations; correlation length "
        f"{base.multipath_field_length} m, not fitted)."
    )
    print("   sigma cm   static misfit (mean squared log ratio)   mean ratio per estimator")
    fits = []
    for sigma in FIT_SIGMAS if args.sigma is None else (args.sigma,):
        model = dataclasses.replace(base, multipath_field_sigma=sigma)
        rows = static_rows(model, installations, args.seed)
        fits.append((_log_misfit(rows), sigma, rows))
        print(f"   {100 * sigma:8.1f}   {_log_misfit(rows):10.3f}{'':30}{_summary(rows)}")
    _, sigma, fit = min(fits, key=lambda f: f[0])
    model = dataclasses.replace(base, multipath_field_sigma=sigma)
    _print(fit, f"Static tables (fit): multipath sigma {100 * sigma:.1f} cm")
    holdout = moving_rows(model, 1 if args.quick else 3, args.seed + 1, args.quick)
    _print(holdout, "Moving tables (held out, the fitted model unchanged)")
    before = moving_rows(base, 1 if args.quick else 3, args.seed + 1, args.quick)

    def gap(ls_raw: bool) -> float:
        """Mean over the static tables of the LS / WLS-T error ratio per axis."""
        rng = np.random.default_rng(args.seed)
        errors = [static_errors(model, t, installations, rng, ls_raw) for t in STATIC_TABLES]
        return float(np.mean([np.mean(e["ls"] / e["wls-t"]) for e in errors]))

    paper_gap = np.mean([np.mean(np.divide(*STATIC_TABLES[t][-1].values())) for t in STATIC_TABLES])
    print(
        f"\nStatic LS / WLS-T error: paper {paper_gap:.2f}; simulated with LS on the raw "
        f"ranges {gap(True):.2f}, with LS fed the calibrated ranges too {gap(False):.2f}"
    )
    print("\nMean ratio simulated / paper, per estimator (min-max):")
    print(f"   static, fit:                    {_summary(fit)}")
    print(f"   moving, held out:               {_summary(holdout)}")
    print(f"   moving, without the multipath:  {_summary(before)}")
    lidar = lidar_rows(args.quick, args.seed)
    structure_table(2 if args.quick else 15)
    blocked_visit_table(10 if args.quick else 200)
    if args.json:
        args.json.write_text(json.dumps(fit + holdout + lidar, indent=1))
        print(f"wrote {args.json}")


def lidar_rows(quick: bool, seed: int) -> list[dict]:
    """Fit the LiDAR channel bias on section IV-A's moving RMSE, check table I; print both."""
    runs, moving_runs, scans = (4, 1, 8) if quick else (30, 6, 40)
    sigmas = (LIDAR_BIAS_SIGMAS[2],) if quick else LIDAR_BIAS_SIGMAS
    print(
        f"\nLiDAR ICP, paper 000. Fit: the channel range bias on section IV-A's moving "
        f"end-effector (RMSE over {moving_runs} runs of {scans} scans); beam divergence "
        f"{1000 * LIDAR_FIXED.beam_divergence:.0f} mrad, incidence up to "
        f"{LIDAR_FIXED.max_incidence_deg:.0f} deg, not fitted."
    )
    print("   bias cm   RMSE cm   ratio   failed scans")
    fits = []
    for sigma in sigmas:
        errors = dataclasses.replace(LIDAR_FIXED, channel_bias_sigma=sigma)
        rmse, failed = moving_rmse(errors, moving_runs, scans, seed + 1)
        row = _row("IV-A moving", "icp", "xyz", ICP_RMSE_CM, rmse, "fit", paper="000")
        fits.append((_log_misfit([row]), sigma, row))
        print(f"   {100 * sigma:7.1f}   {100 * rmse:7.2f}   {rmse / 0.01 / ICP_RMSE_CM:5.2f}"
              f"   {failed}")  # fmt: skip
    _, sigma, fit = min(fits, key=lambda f: f[0])
    errors = dataclasses.replace(LIDAR_FIXED, channel_bias_sigma=sigma)
    _print([fit], f"Section IV-A moving end-effector (fit): channel bias {100 * sigma:.1f} cm")
    holdout = lidar_static_rows(errors, runs, seed)
    _print(holdout, f"Table I outdoor (held out; {runs} runs of a stationary sensor)")
    return [fit, *holdout, *kinematics_rows(quick, seed)]


def kinematics_rows(quick: bool, seed: int) -> list[dict]:
    """Fit the excavator's GNSS error on section IV-A's kinematics-only RMSE; check its
    largest error; print both and the share within 1 cm."""
    runs, seconds = (2, 20.0) if quick else (12, 60.0)
    sigmas = (GNSS_SIGMAS[1],) if quick else GNSS_SIGMAS
    base = ExcavatorErrors()
    ratio = base.gnss_sigma_z / base.gnss_sigma_xy
    print(
        f"\nKinematics only, paper 000 section IV-A. Fit: the base's RTK GNSS error (horizontal "
        f"sigma, vertical {ratio:.2f} times it) on the RMSE over {runs} machines of "
        f"{seconds:.0f} s; joints, turn encoder, heading and link lengths as "
        "ExcavatorErrors' defaults, not fitted."
    )
    print("   GNSS cm   RMSE cm   ratio   max cm   within 1 cm")
    fits = []
    for sigma in sigmas:
        errors = dataclasses.replace(base, gnss_sigma_xy=sigma, gnss_sigma_z=ratio * sigma)
        e = kinematics_errors(errors, runs, seconds, seed + 2)
        rmse = float(np.sqrt(np.mean(np.sum(e**2, axis=-1))))
        worst = float(np.median(np.max(np.linalg.norm(e, axis=-1), axis=1)))
        within = float(np.mean(np.abs(e) <= 0.01))
        row = _row("IV-A moving", "kinematics", "xyz", KINEMATICS_RMSE_CM, rmse, "fit", paper="000")
        fits.append((_log_misfit([row]), sigma, row, worst, within))
        print(f"   {100 * sigma:7.2f}   {100 * rmse:7.2f}   {rmse / 0.01 / KINEMATICS_RMSE_CM:5.2f}"
              f"   {100 * worst:6.2f}   {within:10.2f}")  # fmt: skip
    _, sigma, fit, worst, within = min(fits, key=lambda f: f[0])
    _print([fit], f"Section IV-A kinematics (fit): GNSS {100 * sigma:.2f} cm horizontal")
    held = _row("IV-A moving", "kinematics", "max", KINEMATICS_MAX_CM, worst, "holdout", "000")
    _print([held], "Its largest error (held out; the median over the machines of each one's)")
    print(
        f"   share of axis errors within 1 cm: paper {KINEMATICS_WITHIN_1CM:.2f}, "
        f"simulated {within:.2f} (held out; not a length, so not in the JSON rows)"
    )
    return [fit, held]


def structure_table(visits: int) -> None:
    """UWB through the built cabin: the base error per axis and its ratio to the
    reported sigma, with the wood's delay taken off as the design predicts and not."""
    project = load_project(ROOT / "projects" / "cabin")
    setup = project.localization.uwb
    assert setup is not None
    # the cabin is wood: relative permittivity about 2 (docs/uwb.md)
    setup = setup.model_copy(update={"material_delay": WOOD_DELAY})
    project = project.model_copy(
        update={"localization": project.localization.model_copy(update={"uwb": setup})}
    )
    elements = generate_elements(project.elements, project.path)
    plan = make_plan(project, elements)
    stations = {wp.station.id: wp.station for wp in plan.work_packages}
    blocks = [e for e in elements if e.extents is not None]
    print(
        f"\nUWB through the built cabin (material_delay {setup.material_delay}, spread "
        f"{setup.material_delay_spread}; {len(stations)} stations x {visits} visits, "
        "every block built)"
    )
    print(f"   {'delay':<14} {'RMS x y z mm':>22} {'error / sigma x y z yaw':>28}")
    for label, correct in (("taken off", True), ("left on", False)):
        errors, sigmas = [], []
        for sid, station in stations.items():
            for k in range(visits):
                rng = np.random.default_rng(1000 * k + int(sid[1:]))
                _, T = parked_pose(project, station, rng)
                data = simulate_uwb_station(project, T, rng, blocks)
                if not correct:
                    data = dataclasses.replace(data, material_length=None)
                pose = estimate_uwb_station(project, data, sid)
                errors.append(pose_error(pose.T_world_base, T))
                sigmas.append(np.sqrt(np.diag(pose.covariance)))
        rms = np.sqrt(np.mean(np.square(errors), axis=0))
        ratio = rms / np.sqrt(np.mean(np.square(sigmas), axis=0))
        cells = " ".join(f"{1e3 * v:6.1f}" for v in rms[:3])
        ratios = " ".join(f"{v:5.2f}" for v in ratio[[0, 1, 2, 5]])
        print(f"   {label:<14} {cells:>22} {ratios:>28}")


def blocked_visit_table(n: int) -> None:
    """The UWB global test where the structure blocks most lines of sight: the cabin's
    visit with the most blocked links, localized ``n`` times (each with its own
    installation and parking), against the same station with nothing built."""
    project = load_project(ROOT / "projects" / "cabin")
    study = prepare_study(project, "uwb")
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    blocked = []
    for v, station in enumerate(study.stations):
        T = station.T_world_base(T_platform_base)
        rng = np.random.default_rng(v)
        data = simulate_uwb_station(
            project, T, rng, study.built_before[v], **study.visit_arguments[v]
        )
        blocked.append(0 if data.occluded is None else int(data.occluded.sum()))
    v = int(np.argmax(blocked))
    print(
        f"\nUWB global test at the cabin's visit {v + 1} ({blocked[v]} of 8 links blocked), "
        f"{n} localizations each (alpha 0.001)"
    )
    head = f"   {'built':<14} {'p < 0.1':>8} {'p < 0.01':>9} {'mean p':>7}"
    print(f"{head}   (expected 0.10, 0.01, 0.50)")
    for label, built in (("as planned", study.built_before[v]), ("nothing", ())):
        rng = np.random.default_rng(7)
        p_values = []
        for _ in range(n):
            installation = uwb_station.draw_installation(project, rng)
            _, T = parked_pose(project, study.stations[v], rng)
            data = simulate_uwb_station(project, T, rng, built, installation=installation,
                                        **study.visit_arguments[v])  # fmt: skip
            pose = estimate_uwb_station(project, data, study.stations[v].id)
            p_values.append(pose.integrity.global_test["p_value"])
        p = np.array(p_values)
        print(f"   {label:<14} {np.mean(p < 0.1):8.3f} {np.mean(p < 0.01):9.3f} {p.mean():7.2f}")


if __name__ == "__main__":
    main()
