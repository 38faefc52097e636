"""UWB measurement files: readers and writers of ranges and IMU records.

The computation of ``fabflow localize uwb`` over these files is
:mod:`fabflow.localize.uwb_files`.

Files
-----
RANGES.csv
    One range per line, header ``t,anchor,range`` plus an optional ``tag``
    column: time in seconds (non-decreasing), anchor id as in the anchors file,
    range in metres, tag as the 0-based index into the anchors file's ``tags``
    list (0 when the column is absent). A (t, tag, anchor) triple may appear once.
ANCHORS.yaml
    The ``localization.uwb`` section of a project (``anchors``, ``T_world_uwb``,
    ``sigma``, ``tags``, ``calibration``, ...) and optionally ``T_platform_base``
    (a pose ``{xyz, abc_deg}``; identity when absent, which makes the result
    the platform pose).
IMU.csv
    Header ``t,ax,ay,az,gx,gy,gz``: time (s, strictly increasing, gaps of at most
    ``MAX_IMU_GAP_S``), specific force (m/s^2, norm at most
    ``MAX_SPECIFIC_FORCE``) and angular rate (rad/s, norm at most
    ``MAX_ANGULAR_RATE``) in the platform frame (bounds in
    :mod:`fabflow.positioning.eskf_input`).

Both are UTF-8 text (a byte order mark is allowed); every problem is an
:class:`~fabflow.errors.InputError` naming the file and, where there is one, the line.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fabflow.errors import InputError
from fabflow.files import csv_rows, read_text
from fabflow.files import show as _show
from fabflow.positioning.eskf_input import imu_problem

RANGE_COLUMNS = ("t", "anchor", "range")
IMU_COLUMNS = ("t", "ax", "ay", "az", "gx", "gy", "gz")


@dataclass(frozen=True)
class RangeLog:
    """Ranges read from a CSV file (arrays of equal length, file order)."""

    t: np.ndarray
    tag: np.ndarray
    anchor: np.ndarray
    range: np.ndarray

    def epochs(self, n_tags: int, n_anchors: int) -> np.ndarray:
        """Group into epochs: the k-th range of each (tag, anchor) pair goes to epoch k.

        Returns (n_epochs, n_tags, n_anchors) with NaN where a pair has fewer ranges.
        """
        key = self.tag * n_anchors + self.anchor
        order = np.argsort(key, kind="stable")
        sorted_key = key[order]
        starts = np.searchsorted(sorted_key, sorted_key, side="left")
        k = np.empty_like(key)
        k[order] = np.arange(key.size) - starts
        out = np.full((int(k.max()) + 1, n_tags, n_anchors), np.nan)
        out[k, self.tag, self.anchor] = self.range
        return out


def _read_csv(
    path: Path, required: tuple[str, ...]
) -> tuple[list[str], Iterator[tuple[int, list[str]]]]:
    """The stripped header and an iterator over ``(line number, fields)`` of the data rows."""
    rows = csv_rows(read_text(path), path)
    first = next(rows, None)
    if first is None:
        raise InputError("the file is empty; expected a header line", path, "line 1")
    header = [h.strip() for h in first[1]]
    missing = [c for c in required if c not in header]
    if missing:
        raise InputError(
            f"missing column(s) {', '.join(missing)}; expected a header with "
            f"{', '.join(required)} (got {_show(', '.join(header), 200)})",
            path,
            f"line {first[0]}",
        )
    return header, rows


def _float(value: str, path: Path, line: int, column: str) -> float:
    try:
        x = float(value)
    except ValueError:
        raise InputError(
            f"column '{column}': {_show(value)} is not a number", path, f"line {line}"
        ) from None
    if not math.isfinite(x):
        raise InputError(f"column '{column}': {_show(value)} is not finite", path, f"line {line}")
    return x


def read_ranges_csv(path: str | Path, anchor_ids: list[str], n_tags: int) -> RangeLog:
    """Read and check a RANGES.csv file (see the module docstring).

    Raises
    ------
    InputError
        A file that is not UTF-8 text or not CSV, missing columns, malformed
        numbers, unsorted or duplicate timestamps, unknown anchor ids or tag
        indices, negative ranges; the message names the file and the line.
    """
    path = Path(path)
    index = {a: i for i, a in enumerate(anchor_ids)}
    header, rows = _read_csv(path, RANGE_COLUMNS)
    col = {h: i for i, h in enumerate(header)}
    has_tag = "tag" in col
    ts, tags, anchors, ranges = [], [], [], []
    seen: set[tuple[int, int]] = set()
    t_prev = -math.inf
    for line, row in rows:
        if len(row) != len(header):
            raise InputError(f"expected {len(header)} values, got {len(row)}", path, f"line {line}")
        t = _float(row[col["t"]], path, line, "t")
        a_id = row[col["anchor"]].strip()
        if a_id not in index:
            raise InputError(
                f"unknown anchor id {_show(a_id)}; the anchors file has {', '.join(anchor_ids)}",
                path,
                f"line {line}",
            )
        r = _float(row[col["range"]], path, line, "range")
        if r < 0:
            raise InputError(f"range {r} is negative", path, f"line {line}")
        tag = 0
        if has_tag:
            raw = row[col["tag"]].strip()
            ok = raw.isascii() and raw.isdigit() and len(raw) < 10
            if not ok or int(raw) >= n_tags:
                raise InputError(
                    f"tag {_show(raw)} is not an index into the {n_tags} tag(s) of the anchors "
                    f"file (0..{n_tags - 1})",
                    path,
                    f"line {line}",
                )
            tag = int(raw)
        if t < t_prev:
            raise InputError(
                f"timestamps are not sorted: t = {t} after t = {t_prev}", path, f"line {line}"
            )
        if t > t_prev:
            seen.clear()
        key = (tag, index[a_id])
        if key in seen:
            raise InputError(
                f"duplicate timestamp t = {t} for tag {tag}, anchor {a_id}",
                path,
                f"line {line}",
            )
        seen.add(key)
        t_prev = t
        ts.append(t)
        tags.append(tag)
        anchors.append(index[a_id])
        ranges.append(r)
    if not ts:
        raise InputError("no ranges in the file", path)
    return RangeLog(
        t=np.array(ts), tag=np.array(tags), anchor=np.array(anchors), range=np.array(ranges)
    )


def read_imu_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read an IMU.csv file: (t (M,), accel (M, 3), gyro (M, 3)).

    Raises
    ------
    InputError
        A file that is not UTF-8 text or not CSV, missing columns, malformed or
        non-finite numbers, timestamps not strictly increasing, gaps, values
        beyond what an IMU measures (:func:`~fabflow.positioning.eskf_input.imu_problem`),
        fewer than two samples; the message names the file and the line.
    """
    path = Path(path)
    header, records = _read_csv(path, IMU_COLUMNS)
    col = [header.index(c) for c in IMU_COLUMNS]
    rows, lines = [], []
    t_prev = -math.inf
    for line, row in records:
        if len(row) != len(header):
            raise InputError(f"expected {len(header)} values, got {len(row)}", path, f"line {line}")
        vals = [_float(row[i], path, line, c) for i, c in zip(col, IMU_COLUMNS, strict=True)]
        if vals[0] < t_prev:
            raise InputError(
                f"timestamps are not sorted: t = {vals[0]} after t = {t_prev}",
                path,
                f"line {line}",
            )
        if vals[0] == t_prev:
            raise InputError(f"duplicate timestamp t = {vals[0]}", path, f"line {line}")
        t_prev = vals[0]
        rows.append(vals)
        lines.append(line)
    if len(rows) < 2:
        raise InputError("an IMU file needs at least two samples", path)
    data = np.array(rows)
    t, accel, gyro = data[:, 0], data[:, 1:4], data[:, 4:7]
    problem = imu_problem(t, accel, gyro)
    if problem is not None:
        raise InputError(problem[1], path, f"line {lines[problem[0]]}")
    return t, accel, gyro


def write_ranges_csv(
    path: str | Path,
    t: np.ndarray,
    tag: np.ndarray,
    anchor: np.ndarray,
    ranges: np.ndarray,
    anchor_ids: list[str],
) -> Path:
    """Write ranges in the RANGES.csv format, sorted by time (millimetre resolution)."""
    path = Path(path)
    order = np.argsort(t, kind="stable")
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "tag", "anchor", "range"])
        for i in order:
            w.writerow([f"{t[i]:.6f}", int(tag[i]), anchor_ids[int(anchor[i])], f"{ranges[i]:.4f}"])
    return path


def write_imu_csv(path: str | Path, t: np.ndarray, accel: np.ndarray, gyro: np.ndarray) -> Path:
    """Write IMU samples in the IMU.csv format."""
    path = Path(path)
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(IMU_COLUMNS)
        for ti, a, g in zip(t, accel, gyro, strict=True):
            w.writerow([f"{ti:.6f}", *(f"{v:.6f}" for v in a), *(f"{v:.7f}" for v in g)])
    return path
