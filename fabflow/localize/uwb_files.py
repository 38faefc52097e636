"""UWB localization from measured files: the computation behind ``fabflow localize uwb``.

Ranges (CSV), the anchors file (YAML: the ``localization.uwb`` section plus
``T_platform_base``) and optionally an IMU record (CSV) give the arm base pose.
Without an IMU the platform is taken as standing still
(:func:`~fabflow.positioning.uwb_platform.locate_platform`); with one the
UWB/IMU ESKF (:mod:`fabflow.positioning.eskf`) runs over the whole record.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import ValidationError

from fabflow.errors import InputError
from fabflow.localize.site import anchors_world
from fabflow.positioning.eskf import (
    Eskf,
    EskfParams,
    default_covariance,
    initial_attitude,
    pose_covariance_world,
    run_eskf,
)
from fabflow.positioning.eskf_input import coverage_problem
from fabflow.positioning.eskf_integrity import eskf_integrity
from fabflow.positioning.integrity import Integrity
from fabflow.positioning.result import BasePose
from fabflow.positioning.uwb import UNOBSERVED_VARIANCE, Sigma, locate
from fabflow.positioning.uwb_calibration import (
    RangeCalibration,
    reject_outliers,
    reject_outliers_static,
)
from fabflow.positioning.uwb_io import RangeLog, read_imu_csv, read_ranges_csv
from fabflow.positioning.uwb_platform import (
    heading_from_motion,
    locate_platform,
    platform_to_base_covariance,
    rejected_ranges,
)
from fabflow.project import UwbSetup, format_loc
from fabflow.robots import platform
from fabflow.schema import PoseSpec
from fabflow.sensors.uwb import UwbErrorModel
from fabflow.transforms.se3 import compose_covariance
from fabflow.transforms.so3 import matrix_from_quat, skew


def load_anchors_file(path: str | Path) -> tuple[Any, np.ndarray]:
    """Read ANCHORS.yaml: the UWB setup and ``T_platform_base`` (4x4).

    Raises
    ------
    InputError
        YAML that does not parse or fields that do not validate (with the field path).
    """

    path = Path(path)
    if not path.exists():
        raise InputError("file does not exist", path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read file: {exc}", path) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark else None
        raise InputError(
            f"YAML does not parse: {getattr(exc, 'problem', exc)}", path, where
        ) from None
    if not isinstance(data, dict):
        raise InputError("expected a mapping with 'anchors' (and optional UWB settings)", path)
    data = dict(data)
    pose = data.pop("T_platform_base", None)
    try:
        setup = UwbSetup.model_validate(data)
        T_platform_base = PoseSpec.model_validate(pose or {}).matrix()
    except ValidationError as exc:
        msgs = [f"{format_loc(e['loc'])}: {e['msg']}" for e in exc.errors()]
        raise InputError("invalid anchors file\n  " + "\n  ".join(msgs), path) from None
    return setup, T_platform_base


def localize_from_files(
    ranges_csv: str | Path, anchors_yaml: str | Path, imu_csv: str | Path | None = None
) -> BasePose:
    """The computation behind ``fabflow localize uwb``.

    Without an IMU the platform is taken as standing still: all ranges give one
    ``x, y, z, yaw`` (two or more tags needed for the heading). With an IMU the
    ESKF runs over the whole record and the pose at its end is returned; with a
    single tag its initial heading is the direction of the first motion (the
    platform drives along its x axis). The ESKF pose carries the filter's tests
    as its integrity record (:mod:`fabflow.positioning.eskf_integrity`); an IMU
    record beyond what an IMU measures, or one that does not cover the ranges,
    is an InputError.
    """
    setup, T_platform_base = load_anchors_file(anchors_yaml)
    ids, A = anchors_world(setup)
    L = np.asarray(setup.tags, dtype=float)
    log = read_ranges_csv(ranges_csv, ids, len(L))
    cal = RangeCalibration.from_mapping(
        {k: {"offset": v[0], "scale": v[1]} for k, v in setup.calibration.items()},
        ids,
        str(anchors_yaml),
    )
    sigma = UwbErrorModel(sigma_1m=setup.sigma).sigma
    epochs = cal.apply(log.epochs(len(L), len(ids)))
    quality: dict[str, Any] = {
        "n_ranges": int(log.range.size),
        "n_tags": len(L),
        "n_anchors": len(ids),
        "calibration": cal.to_dict(ids),
    }
    integrity: Integrity | None = None
    if imu_csv is None:
        rej = reject_outliers_static(epochs, sigma(epochs))
        T_world_platform, cov, residuals, more = _static_pose(
            setup, A, L, rej, sigma, T_platform_base, ids
        )
        integrity = more.pop("integrity")
    else:
        rej = reject_outliers(epochs, sigma(epochs))
        corrected = cal.apply_indexed(log.range, log.anchor)
        T_world_platform, cov, residuals, more, integrity = _eskf_pose(
            setup, A, L, rej, sigma, T_platform_base, log, corrected, imu_csv
        )
    quality.update(more)
    T_world_base = platform.T_world_base(T_world_platform, 0.0, T_platform_base)
    rmse = float(np.sqrt(np.mean(residuals**2))) if residuals.size else 0.0
    return BasePose(
        T_world_base=T_world_base,
        covariance=0.5 * (cov + cov.T),
        method="uwb",
        residuals=np.asarray(residuals)[:, None],
        rmse=rmse,
        quality=quality,
        integrity=integrity,
    )


def _static_pose(
    setup: UwbSetup,
    A: np.ndarray,
    L: np.ndarray,
    rej: Any,
    sigma: Sigma,
    T_platform_base: np.ndarray,
    anchor_ids: list[str],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """Platform pose, base covariance, residuals and quality (with the integrity record)."""
    estimator = "wls-t" if setup.estimator in ("wls-t", "eskf") else setup.estimator
    fix = locate_platform(
        A,
        rej.ranges,
        L,
        sigma,
        method=estimator,
        anchor_bias_sigma=np.full(len(A), setup.calibration_sigma),
        anchor_ids=anchor_ids,
        base_lever=T_platform_base[:3, 3],
    )
    cov = platform_to_base_covariance(fix.T, T_platform_base, fix.covariance)
    quality = {
        "estimator": estimator,
        "solver": "static platform: joint Gauss-Newton over all ranges",
        "n_rejected_robust_centre": int(rej.rejected.sum()),
        "n_used": fix.n_used,
        "std_xyz_yaw": [float(v) for v in np.sqrt(np.diag(fix.covariance))],
        "unobserved": ["rx", "ry"] + ([] if fix.heading_observed else ["rz"]),
        "unobserved_variance_rad2": UNOBSERVED_VARIANCE,
        "integrity": None
        if fix.integrity is None
        else fix.integrity.with_checks(rejected_ranges=rejected_ranges(rej.rejected, anchor_ids)),
    }
    return fix.T, cov, fix.residuals, quality


def _eskf_pose(
    setup: UwbSetup,
    A: np.ndarray,
    L: np.ndarray,
    rej: Any,
    sigma: Sigma,
    T_platform_base: np.ndarray,
    log: RangeLog,
    corrected: np.ndarray,
    imu_csv: str | Path,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any], Integrity]:
    """Platform pose at the end of the record, covariance, residuals, quality, integrity (ESKF)."""
    t_imu, acc, gyr = read_imu_csv(imu_csv)
    use = np.isfinite(log.range)
    coverage = coverage_problem(t_imu, log.t[use])
    if coverage is not None:
        raise InputError(coverage, imu_csv)
    t0 = t_imu[0]
    first = rej.ranges[: max(10, int(setup.rate_hz))]
    if len(L) >= 2:
        pf = locate_platform(A, first, L, sigma)
        p0, yaw0, s_yaw = pf.T[:3, 3], float(pf.state[3]), math.radians(5.0)
    else:
        fixes = locate(A, rej.ranges[:, 0, :], method="wls-t", sigma=sigma)
        yaw0 = heading_from_motion(fixes.positions[:, :2], 0.3)
        c, s = math.cos(yaw0), math.sin(yaw0)
        lever_w = np.array([c * L[0, 0] - s * L[0, 1], s * L[0, 0] + c * L[0, 1], L[0, 2]])
        p0 = np.nanmedian(fixes.positions[: max(5, int(setup.rate_hz))], axis=0) - lever_w
        s_yaw = math.radians(15.0)
    rest = t_imu < t0 + 0.5
    q0 = initial_attitude(acc[rest] if rest.sum() >= 2 else acc[:2], yaw0)
    filt = Eskf(p0, np.zeros(3), q0, default_covariance(sigma_p=0.3, sigma_yaw=s_yaw), EskfParams())
    track = run_eskf(
        filt,
        t_imu,
        acc,
        gyr,
        log.t[use],
        log.anchor[use],
        corrected[use],
        A,
        sigma,
        tag_index=log.tag[use],
        lever_arms=L,
    )
    T_world_platform = np.eye(4)
    T_world_platform[:3, :3] = matrix_from_quat(track.q[-1])
    T_world_platform[:3, 3] = track.p[-1]
    C_wp = pose_covariance_world(track.q[-1], track.P_final)
    cov = compose_covariance(T_world_platform, C_wp, T_platform_base, None)
    R = T_world_platform[:3, :3]
    tags_w = track.p[-1] + L @ R.T
    res_all = corrected - np.linalg.norm(tags_w[log.tag] - A[log.anchor], axis=1)
    # residuals of the last second against the final pose (the platform has stopped)
    late = log.t >= log.t[-1] - 1.0
    quality = {
        "estimator": "eskf",
        "solver": "UWB/IMU ESKF, per-range updates; pose at the last IMU sample",
        "n_updates": track.n_updates,
        "n_rejected_gate": track.n_rejected,
        "residual_window_s": 1.0,
        "t_end": float(t_imu[-1]),
        "std_xyz_rpy": [float(v) for v in np.sqrt(np.diag(cov))],
        "unobserved": [],
    }
    # the base position's derivative by the error state: dp - R [t]x dtheta
    t_pb = T_platform_base[:3, 3]
    G = np.zeros((3, 15))
    G[:, 0:3] = np.eye(3)
    G[:, 6:9] = -R @ skew(t_pb)
    integrity = eskf_integrity(track.consistency, list(setup.anchors), G, float(t_imu[-1]))
    return T_world_platform, cov, res_all[late], quality, integrity
