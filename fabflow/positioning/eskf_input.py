"""Input bounds of the UWB/IMU ESKF: what an IMU record may contain, and when it fits the ranges.

An IMU reports a bounded specific force and angular rate at a steady rate; a
value far outside (``1e308``), a gap of seconds or an IMU record from another
run cannot give a pose, however well the filter behaves. The bounds are the
constants below; :func:`imu_problem` and :func:`coverage_problem` apply them.
The file reader :func:`~fabflow.positioning.uwb_io.read_imu_csv` names the
line, the filter entry :func:`~fabflow.positioning.eskf.run_eskf` (through
:func:`check_input`) the sample.
"""

from __future__ import annotations

import numpy as np

from fabflow.errors import InputError

MAX_SPECIFIC_FORCE = 1000.0
"""Largest specific force an IMU sample may report (m/s^2, norm of the three axes).

About 100 g: beyond the range of any accelerometer used on a construction
platform (typical ranges are 2-16 g); a larger value is a unit or file error.
"""
MAX_ANGULAR_RATE = 100.0
"""Largest angular rate an IMU sample may report (rad/s, norm), about 5700 deg/s.

MEMS gyros measure up to 2000-4000 deg/s; a platform turns at well under 1 rad/s.
"""
MAX_IMU_GAP_S = 1.0
"""Largest time between two IMU samples (s).

The filter holds each reading until the next one; over a second of unknown
motion the held reading is a guess, not a measurement (at 100 Hz a second is
100 lost samples).
"""
RANGE_MARGIN_S = 0.1
"""How far the ranges may start before or end after the IMU record (s).

The ranges must lie within the IMU's time span: the filter integrates the IMU
between ranges and cannot place a range it has no motion for. The margin allows
for the last few milliseconds of two loggers started and stopped together.
"""


def imu_problem(t: np.ndarray, accel: np.ndarray, gyro: np.ndarray) -> tuple[int, str] | None:
    """The first IMU sample outside what an IMU can report, and why.

    Parameters
    ----------
    t
        (M,) sample times (s), increasing.
    accel, gyro
        (M, 3) specific force (m/s^2) and angular rate (rad/s), body frame.

    Returns
    -------
    ``(index, message)`` of the first offending sample (non-finite values,
    ``|a| > MAX_SPECIFIC_FORCE``, ``|w| > MAX_ANGULAR_RATE``, a gap larger than
    ``MAX_IMU_GAP_S`` before it), or ``None`` when every sample is possible.
    """
    t = np.asarray(t, dtype=float)
    a = np.asarray(accel, dtype=float)
    w = np.asarray(gyro, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        a_norm = np.sqrt(np.sum(a * a, axis=1))
        w_norm = np.sqrt(np.sum(w * w, axis=1))
        gap = np.r_[0.0, np.diff(t)]
    finite = np.isfinite(t) & np.isfinite(a).all(axis=1) & np.isfinite(w).all(axis=1)
    checks = [
        (~finite, lambda k: "a value is not finite"),
        (
            a_norm > MAX_SPECIFIC_FORCE,
            lambda k: (
                f"specific force |a| = {a_norm[k]:.4g} m/s^2 exceeds what an IMU "
                f"measures ({MAX_SPECIFIC_FORCE:g} m/s^2)"
            ),
        ),
        (
            w_norm > MAX_ANGULAR_RATE,
            lambda k: (
                f"angular rate |w| = {w_norm[k]:.4g} rad/s exceeds what an IMU "
                f"measures ({MAX_ANGULAR_RATE:g} rad/s)"
            ),
        ),
        (
            gap > MAX_IMU_GAP_S,
            lambda k: (
                f"gap of {gap[k]:.4g} s since the previous sample (t = {t[k - 1]:.6g} s) "
                f"exceeds {MAX_IMU_GAP_S:g} s: the motion in between is unknown"
            ),
        ),
    ]
    first: tuple[int, str] | None = None
    for mask, message in checks:
        hits = np.flatnonzero(mask)
        if hits.size and (first is None or hits[0] < first[0]):
            first = (int(hits[0]), message(int(hits[0])))
    return first


def coverage_problem(imu_t: np.ndarray, range_t: np.ndarray) -> str | None:
    """Why the ranges do not lie within the IMU record (``RANGE_MARGIN_S``), or ``None``.

    Parameters
    ----------
    imu_t
        (M,) IMU sample times (s), increasing.
    range_t
        (K,) range times (s); no ranges is no problem.
    """
    rt = np.asarray(range_t, dtype=float)
    if rt.size == 0:
        return None
    lo, hi = float(imu_t[0]), float(imu_t[-1])
    r0, r1 = float(rt.min()), float(rt.max())
    if lo - RANGE_MARGIN_S <= r0 and r1 <= hi + RANGE_MARGIN_S:
        return None
    return (
        f"the IMU record (t = {lo:.6g} to {hi:.6g} s) does not cover the ranges "
        f"(t = {r0:.6g} to {r1:.6g} s; at most {RANGE_MARGIN_S:g} s outside allowed): "
        "are both files from the same run and clock?"
    )


def check_input(
    imu_t: np.ndarray, accel: np.ndarray, gyro: np.ndarray, range_t: np.ndarray
) -> None:
    """Refuse an IMU record the filter cannot use, or one that does not cover the ranges.

    Parameters
    ----------
    imu_t, accel, gyro
        (M,) sample times (s), (M, 3) specific force (m/s^2) and angular rate (rad/s).
    range_t
        (K,) times of the ranges to be applied (s).

    Raises
    ------
    InputError
        Times not strictly increasing or fewer than two samples, arrays of the
        wrong shape, :func:`imu_problem` or :func:`coverage_problem` (naming the
        sample index; the file readers name the line).
    """
    if imu_t.ndim != 1 or imu_t.size < 2 or not np.all(np.diff(imu_t) > 0):
        raise InputError("IMU times must be strictly increasing (at least two samples)")
    if accel.shape != (imu_t.size, 3) or gyro.shape != (imu_t.size, 3):
        raise InputError(f"IMU readings must be ({imu_t.size}, 3) arrays")
    problem = imu_problem(imu_t, accel, gyro)
    if problem is not None:
        raise InputError(f"IMU sample {problem[0]}: {problem[1]}")
    coverage = coverage_problem(imu_t, range_t)
    if coverage is not None:
        raise InputError(coverage)
