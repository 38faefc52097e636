"""UWB localization from measured files: the computation behind ``fabflow localize uwb``.

Ranges (CSV), the anchors file (YAML: the ``localization.uwb`` section plus
``T_platform_base``) and optionally an IMU record (CSV) give the arm base pose.
Without an IMU the platform is taken as standing still
(:func:`~fabflow.positioning.uwb_platform.locate_platform`); with one the
UWB/IMU ESKF (:mod:`fabflow.positioning.eskf`) runs over the whole record.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from fabflow.errors import FabflowError, InputError, LocalizationError
from fabflow.localize.site import anchors_world
from fabflow.localize.uwb_static import static_fix
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
from fabflow.positioning.uwb import (
    UNOBSERVED_VARIANCE,
    Sigma,
    anchor_geometry_problem,
    locate,
)
from fabflow.positioning.uwb_calibration import (
    RangeCalibration,
    reject_outliers,
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
from fabflow.transforms.se3 import compose_covariance
from fabflow.transforms.so3 import matrix_from_quat, skew
from fabflow.yaml_input import read_yaml

MAX_ANCHORS_BYTES = 64 * 2**10
"""Largest anchors file read (bytes): a setup of two dozen anchors takes two kilobytes."""
MAX_ANCHORS = 24
"""Most anchors an anchors file may list (a site has 4 to a dozen)."""
MAX_TAGS = 8
"""Most tags on the platform (two give the heading; four are plenty)."""
MIN_SIGMA_M = 1e-4
"""Smallest range noise ``sigma`` (metres at 1 m): no UWB ranges to a tenth of a millimetre."""
MAX_LENGTH_M = 10_000.0
"""Largest magnitude of a length in the anchors file (metres): coordinates, lever arms,
calibration offsets and sigmas; 10 km is far beyond the reach of UWB ranging."""
MAX_STATIC_RANGES = 20_000
"""Most ranges of a static localization (no IMU): 40 s of a platform standing still,
ranged at 60 Hz from four anchors to two tags. The joint adjustment refits all of
them once per anchor it tests, so a longer stand adds work, not accuracy."""
MAX_EPOCH_CELLS = 20_000_000
"""Largest table of ranges by epoch, tag and anchor the estimators build (160 MB)."""
SCALE_BOUNDS = (0.5, 2.0)
"""Range of a ranging calibration scale: a scale error of a factor two is not a calibration."""


def load_anchors_file(path: str | Path) -> tuple[UwbSetup, np.ndarray]:
    """Read ANCHORS.yaml: the UWB setup and ``T_platform_base`` (4x4).

    The file is read safely (:func:`fabflow.yaml_input.read_yaml`: at most
    :data:`MAX_ANCHORS_BYTES`, bounded nesting, no duplicate keys, finite
    numbers) and validated as the project's ``localization.uwb`` section; its
    sizes and lengths are bounded (:data:`MAX_ANCHORS`, :data:`MAX_TAGS`,
    :data:`MIN_SIGMA_M`, :data:`MAX_LENGTH_M`, :data:`SCALE_BOUNDS`).

    Raises
    ------
    InputError
        YAML that does not parse or fields that do not validate, each with
        its line and field path.
    """
    doc = read_yaml(path, "anchors file", MAX_ANCHORS_BYTES, finite=True)
    data = doc.data
    if not isinstance(data, dict):
        raise InputError(
            "expected a mapping with 'anchors' (and optional UWB settings)", path, "line 1"
        )
    data = dict(data)
    pose = data.pop("T_platform_base", None)
    problems: list[tuple[tuple[Any, ...], str]] = []
    try:
        setup = UwbSetup.model_validate(data)
    except ValidationError as exc:
        problems += [(tuple(e["loc"]), e["msg"]) for e in exc.errors()]
    try:
        T_platform_base = PoseSpec.model_validate({} if pose is None else pose).matrix()
    except ValidationError as exc:
        problems += [(("T_platform_base", *e["loc"]), e["msg"]) for e in exc.errors()]
    if not problems:
        problems = _out_of_bounds(setup, T_platform_base)
    if problems:
        # pydantic's messages may quote the file (an unknown anchor id): keep them short
        problems = [(loc, _short(msg)) for loc, msg in problems]
        lines = []
        for loc, msg in problems[:10]:
            line = doc.line_of(loc)
            lines.append(f"{'' if line is None else f'line {line}: '}{_field(loc)}: {msg}")
        if len(lines) == 1:
            loc, msg = problems[0]
            line = doc.line_of(loc)
            raise InputError(
                f"{_field(loc)}: {msg}", path, None if line is None else f"line {line}"
            )
        more = [f"... and {len(problems) - 10} more"] if len(problems) > 10 else []
        raise InputError("invalid anchors file\n  " + "\n  ".join(lines + more), path)
    return setup, T_platform_base


def _short(message: str) -> str:
    """``message`` with every long word and the whole cut short (it may quote the file)."""
    message = re.sub(r"\S{41,}", lambda m: m.group()[:40] + "...", message)
    return message if len(message) <= 200 else message[:200] + "..."


def _field(loc: tuple[Any, ...]) -> str:
    """The field path of ``loc``, keys from the file shortened."""
    return format_loc(
        tuple(k if not isinstance(k, str) or len(k) <= 40 else k[:40] + "..." for k in loc)
    )


def _floats(data: Any, loc: tuple[Any, ...] = ()) -> list[tuple[tuple[Any, ...], float]]:
    """Every float in plain data with its field path."""
    if isinstance(data, float):
        return [(loc, data)]
    if isinstance(data, dict):
        return [x for k, v in data.items() for x in _floats(v, (*loc, k))]
    if isinstance(data, list | tuple):
        return [x for i, v in enumerate(data) for x in _floats(v, (*loc, i))]
    return []


def _out_of_bounds(
    setup: UwbSetup, T_platform_base: np.ndarray
) -> list[tuple[tuple[Any, ...], str]]:
    """Field paths and messages of the values beyond the bounds of an anchors file."""
    floats = _floats(setup.model_dump())
    out = [(loc, f"{v} is not finite") for loc, v in floats if not math.isfinite(v)]
    if out:
        return out  # a text such as 'nan' the model read as a number
    if not setup.anchors:
        out.append((("anchors",), "names no anchors: measured ranges need the surveyed anchors"))
    if len(setup.anchors) > MAX_ANCHORS:
        out.append((("anchors",), f"{len(setup.anchors)} anchors, more than {MAX_ANCHORS}"))
    if len(setup.tags) > MAX_TAGS:
        out.append((("tags",), f"{len(setup.tags)} tags, more than {MAX_TAGS}"))
    if not np.all(np.isfinite(T_platform_base)):
        out.append((("T_platform_base",), "is not a finite pose"))
    lengths: list[tuple[tuple[Any, ...], float]] = [
        *((("anchors", k, i), v) for k, xyz in setup.anchors.items() for i, v in enumerate(xyz)),
        *((("tags", j, i), v) for j, xyz in enumerate(setup.tags) for i, v in enumerate(xyz)),
        *((("T_world_uwb", "xyz", i), v) for i, v in enumerate(setup.T_world_uwb.xyz)),
        *((("T_platform_base", "xyz", i), float(v)) for i, v in enumerate(T_platform_base[:3, 3])),
        *((("calibration", k, 0), ab[0]) for k, ab in setup.calibration.items()),
        (("sigma",), setup.sigma),
        (("calibration_sigma",), setup.calibration_sigma),
    ]
    out += [
        (loc, f"{v:.6g} m is beyond the {MAX_LENGTH_M:g} m an anchors file may give")
        for loc, v in lengths
        if abs(v) > MAX_LENGTH_M
    ]
    if setup.sigma < MIN_SIGMA_M:
        out.append((("sigma",), f"{setup.sigma:.6g} m is below {MIN_SIGMA_M:g} m"))
    lo, hi = SCALE_BOUNDS
    out += [
        (("calibration", k, 1), f"scale {ab[1]:.6g} is outside [{lo:g}, {hi:g}]")
        for k, ab in setup.calibration.items()
        if not lo <= ab[1] <= hi
    ]
    return out


def localize_from_files(
    ranges_csv: str | Path, anchors_yaml: str | Path, imu_csv: str | Path | None = None
) -> BasePose:
    """The computation behind ``fabflow localize uwb``.

    Without an IMU the platform is taken as standing still: all ranges give one
    ``x, y, z, yaw`` (two or more tags needed for the heading). With an IMU the
    ESKF runs over the whole record and the pose at its end is returned; with a
    single tag its initial heading is the direction of the first motion (the
    platform drives along its x axis). The ESKF pose carries the filter's tests
    as its integrity record (:mod:`fabflow.positioning.eskf_integrity`).

    Raises
    ------
    InputError
        A problem of one of the files (naming it, and the line where there is
        one): see :func:`load_anchors_file`,
        :func:`~fabflow.positioning.uwb_io.read_ranges_csv` and
        :func:`~fabflow.positioning.uwb_io.read_imu_csv`; an IMU record that does
        not cover the ranges; a static record of more than
        :data:`MAX_STATIC_RANGES` ranges; more than :data:`MAX_EPOCH_CELLS` cells of
        epochs.
    LocalizationError
        Anchors that cannot fix a position (naming the anchors file), or ranges
        that give no pose (naming the ranges file).
    """
    setup, T_platform_base = load_anchors_file(anchors_yaml)
    ids, A = anchors_world(setup)
    problem = anchor_geometry_problem(A)
    if problem is not None:
        raise LocalizationError(problem, anchors_yaml)
    L = np.asarray(setup.tags, dtype=float)
    log = read_ranges_csv(ranges_csv, ids, len(L))
    if imu_csv is None and log.range.size > MAX_STATIC_RANGES:
        raise InputError(
            f"{log.range.size} ranges, more than the {MAX_STATIC_RANGES} of a static "
            "localization: give the ranges of one stand (or an IMU record of the motion)",
            ranges_csv,
        )
    n_epochs = int(np.bincount(log.tag * len(ids) + log.anchor).max())
    if n_epochs * len(L) * len(ids) > MAX_EPOCH_CELLS:
        raise InputError(
            f"one tag-anchor pair has {n_epochs} ranges: with {len(L)} tag(s) and "
            f"{len(ids)} anchors the table of epochs would exceed {MAX_EPOCH_CELLS} cells",
            ranges_csv,
        )
    try:
        return _localize(setup, T_platform_base, ids, A, L, log, anchors_yaml, imu_csv)
    except FabflowError as exc:
        if exc.source is not None:
            raise
        # a problem of the estimation: the ranges did not give a pose
        raise type(exc)(exc.message, ranges_csv, exc.location) from None


def _localize(
    setup: UwbSetup,
    T_platform_base: np.ndarray,
    ids: list[str],
    A: np.ndarray,
    L: np.ndarray,
    log: RangeLog,
    anchors_yaml: str | Path,
    imu_csv: str | Path | None,
) -> BasePose:
    """:func:`localize_from_files` once the files are read."""
    cal = RangeCalibration.from_mapping(
        {k: {"offset": v[0], "scale": v[1]} for k, v in setup.calibration.items()},
        ids,
        str(anchors_yaml),
    )
    # a moving platform meets fresh multipath as it goes: its ranges weigh by the whole error
    sigma = setup.error_model().total_sigma
    epochs = cal.apply(log.epochs(len(L), len(ids)))
    quality: dict[str, Any] = {
        "n_ranges": int(log.range.size),
        "n_tags": len(L),
        "n_anchors": len(ids),
        "calibration": cal.to_dict(ids),
    }
    integrity: Integrity | None = None
    if imu_csv is None:
        T_world_platform, cov, residuals, more = _static_pose(
            setup, A, L, epochs, T_platform_base, ids
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
    epochs: np.ndarray,
    T_platform_base: np.ndarray,
    anchor_ids: list[str],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """Platform pose, base covariance, residuals and quality (with the integrity record)
    of the calibrated ranges ``epochs``: the estimate of a simulated station
    (:func:`~fabflow.localize.uwb_static.static_fix`)."""
    estimator = "wls-t" if setup.estimator in ("wls-t", "eskf") else setup.estimator
    model = setup.error_model()
    fix, rej = static_fix(
        model,
        A,
        epochs,
        L,
        model.field_sigma,
        np.full(len(A), setup.calibration_sigma),
        method=estimator,
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
