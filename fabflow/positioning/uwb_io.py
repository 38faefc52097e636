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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fabflow.errors import InputError
from fabflow.files import CsvTable, csv_table
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


MAX_RANGES_BYTES = 64 * 2**20
"""Largest RANGES.csv read (bytes)."""
MAX_RANGES = 1_000_000
"""Most ranges in a RANGES.csv: over an hour at 60 Hz from four anchors (the ESKF
applies each one in turn, about 25 us apiece)."""
MAX_IMU_BYTES = 64 * 2**20
"""Largest IMU.csv read (bytes)."""
MAX_IMU_SAMPLES = 1_000_000
"""Most samples in an IMU.csv: close to three hours at 100 Hz."""
MAX_RANGE_M = 1000.0
"""Longest range accepted (metres): UWB ranges reach a few hundred metres at most."""


def _table(
    path: Path, required: tuple[str, ...], what: str, max_bytes: int, max_rows: int
) -> CsvTable:
    """The CSV file as columns, with the ``required`` columns present."""
    table = csv_table(path, what, max_bytes, max_rows)
    missing = [c for c in required if c not in table.columns]
    if missing:
        raise InputError(
            f"missing column(s) {', '.join(missing)}; expected a header with "
            f"{', '.join(required)} (got {_show(', '.join(table.header), 80)})",
            path,
            f"line {table.header_line}",
        )
    return table


def _first(mask: np.ndarray) -> int | None:
    """Index of the first True in ``mask``, or ``None``."""
    hits = np.flatnonzero(mask)
    return int(hits[0]) if hits.size else None


def read_ranges_csv(path: str | Path, anchor_ids: list[str], n_tags: int) -> RangeLog:
    """Read and check a RANGES.csv file (see the module docstring).

    The file holds at most :data:`MAX_RANGES_BYTES` bytes and :data:`MAX_RANGES`
    ranges, each between 0 and :data:`MAX_RANGE_M` metres.

    Raises
    ------
    InputError
        A file that is not UTF-8 text or not CSV, missing columns, malformed
        numbers, unsorted or duplicate timestamps, unknown anchor ids or tag
        indices, negative or impossibly long ranges, too many rows; the message
        names the file and the line.
    """
    path = Path(path)
    table = _table(path, RANGE_COLUMNS, "ranges file", MAX_RANGES_BYTES, MAX_RANGES)
    if len(table) == 0:
        raise InputError("no ranges in the file", path)
    t = table.numbers("t")
    anchor = _lookup(table, "anchor", {a: i for i, a in enumerate(anchor_ids)}, anchor_ids)
    r = table.numbers("range")
    if (k := _first(r < 0)) is not None:
        raise InputError(f"range {r[k]} is negative", path, table.at(k))
    if (k := _first(r > MAX_RANGE_M)) is not None:
        raise InputError(
            f"range {r[k]:.6g} m is longer than UWB ranges reach ({MAX_RANGE_M:g} m)",
            path,
            table.at(k),
        )
    tag = np.zeros(len(table), dtype=np.int64)
    if "tag" in table.columns:
        valid = {str(j): j for j in range(n_tags)}
        tag = _lookup(table, "tag", valid, None, n_tags)
    if (k := _first(np.diff(t) < 0)) is not None:
        raise InputError(
            f"timestamps are not sorted: t = {t[k + 1]} after t = {t[k]}", path, table.at(k + 1)
        )
    order = np.lexsort((np.arange(len(t)), anchor, tag, t))
    same = (np.diff(t[order]) == 0) & (np.diff(tag[order]) == 0) & (np.diff(anchor[order]) == 0)
    if same.any():
        k = int(order[1:][same].min())
        raise InputError(
            f"duplicate timestamp t = {t[k]} for tag {tag[k]}, anchor {anchor_ids[anchor[k]]}",
            path,
            table.at(k),
        )
    return RangeLog(t=t, tag=tag, anchor=anchor, range=r)


def _lookup(
    table: CsvTable,
    column: str,
    index: dict[str, int],
    names: list[str] | None,
    n_tags: int = 0,
) -> np.ndarray:
    """The column's stripped fields as indices into ``index``; an unknown one names its line."""
    values, inverse = np.unique(np.asarray(table.columns[column], dtype=str), return_inverse=True)
    codes = np.array([index.get(v.strip(), -1) for v in values.tolist()], dtype=np.int64)
    out = codes[inverse.reshape(-1)]
    if (k := _first(out < 0)) is not None:
        raw = table.columns[column][k].strip()
        if names is not None:
            message = f"unknown anchor id {_show(raw)}; the anchors file has {', '.join(names)}"
        else:
            message = (
                f"tag {_show(raw)} is not an index into the {n_tags} tag(s) of the anchors "
                f"file (0..{n_tags - 1})"
            )
        raise InputError(message, table.source, table.at(k))
    return out


def read_imu_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read an IMU.csv file: (t (M,), accel (M, 3), gyro (M, 3)).

    The file holds at most :data:`MAX_IMU_BYTES` bytes and :data:`MAX_IMU_SAMPLES` samples.

    Raises
    ------
    InputError
        A file that is not UTF-8 text or not CSV, missing columns, malformed or
        non-finite numbers, timestamps not strictly increasing, gaps, values
        beyond what an IMU measures (:func:`~fabflow.positioning.eskf_input.imu_problem`),
        fewer than two samples, too many rows; the message names the file and the line.
    """
    path = Path(path)
    table = _table(path, IMU_COLUMNS, "IMU file", MAX_IMU_BYTES, MAX_IMU_SAMPLES)
    data = np.column_stack([table.numbers(c) for c in IMU_COLUMNS]) if len(table) else None
    if data is None or len(data) < 2:
        raise InputError("an IMU file needs at least two samples", path)
    t, accel, gyro = data[:, 0], data[:, 1:4], data[:, 4:7]
    dt = np.diff(t)
    if (k := _first(dt <= 0)) is not None:
        what = "duplicate timestamp" if dt[k] == 0 else "timestamps are not sorted:"
        raise InputError(f"{what} t = {t[k + 1]} after t = {t[k]}", path, table.at(k + 1))
    problem = imu_problem(t, accel, gyro)
    if problem is not None:
        raise InputError(problem[1], path, table.at(problem[0]))
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
