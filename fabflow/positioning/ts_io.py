"""Files for total station localization: observation CSVs, robot point CSVs, format dispatch.

Observation CSV (one header line, ``#`` comments allowed)::

    point_id,hz_gon,v_gon,slope_distance_m,prism_height_m
    P1,52.33412,96.12005,6.2341,0.0

Angles are ``hz_gon``/``v_gon`` or ``hz_deg``/``v_deg``; ``prism_height_m`` is
optional. Rows may instead give coordinates ``x_m,y_m,z_m`` already computed by
the instrument in its job frame.

Robot point CSV: the prism positions in the robot base frame (from the robot
controller's forward kinematics)::

    point_id,x_m,y_m,z_m
    P1,1.2,0.4,0.9

or the joint values the robot stood at, in degrees, which fabflow turns into
prism positions by forward kinematics of the robot model and the tool::

    point_id,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg
    P1,10,-60,100,0,50,0
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fabflow.errors import InputError
from fabflow.positioning.gsi import parse_gsi
from fabflow.positioning.polar import DEG, GON, Observations


def _read_text(path: Path, what: str) -> str:
    try:
        return path.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise InputError(f"{what} file does not exist", path) from None
    except UnicodeDecodeError:
        raise InputError(f"{what} file is not UTF-8 text", path) from None
    except OSError as exc:
        raise InputError(f"cannot read {what} file: {exc.strerror}", path) from None


def _rows(text: str, source: Path) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """Header (lower-case, stripped) and data rows with their 1-based line numbers."""
    lines = [(i, line) for i, line in enumerate(text.splitlines(), start=1) if line.strip()]
    lines = [(i, line) for i, line in lines if not line.lstrip().startswith("#")]
    if not lines:
        raise InputError("the file is empty (expected a header line and data rows)", source)
    parsed = list(csv.reader(io.StringIO("\n".join(line for _, line in lines))))
    header = [h.strip().lower() for h in parsed[0]]
    rows = [(lines[k][0], [c.strip() for c in parsed[k]]) for k in range(1, len(parsed))]
    return header, rows


def _number(value: str, column: str, source: Path, line: int) -> float:
    if value == "":
        return math.nan
    try:
        x = float(value)
    except ValueError:
        raise InputError(
            f"column {column!r}: {value!r} is not a number", source, f"line {line}"
        ) from None
    if not math.isfinite(x):
        raise InputError(f"column {column!r}: {value!r} is not finite", source, f"line {line}")
    return x


def _id_column(header: list[str], source: Path) -> int:
    for name in ("point_id", "id", "point"):
        if name in header:
            return header.index(name)
    raise InputError(
        f"no point id column (expected 'point_id'); header is {', '.join(header)}",
        source,
        "line 1",
    )


def read_observations_csv(path: str | Path) -> Observations:
    """Read an observation CSV (see the module docstring)."""
    path = Path(path)
    header, rows = _rows(_read_text(path, "observation"), path)
    ic = _id_column(header, path)
    if "hz_gon" in header and "v_gon" in header:
        unit, hz_col, v_col = GON, "hz_gon", "v_gon"
    elif "hz_deg" in header and "v_deg" in header:
        unit, hz_col, v_col = DEG, "hz_deg", "v_deg"
    else:
        unit, hz_col, v_col = 1.0, None, None
    sd_col = next((c for c in ("slope_distance_m", "sd_m") if c in header), None)
    xyz_cols = ("x_m", "y_m", "z_m") if all(c in header for c in ("x_m", "y_m", "z_m")) else None
    if (hz_col is None or sd_col is None) and xyz_cols is None:
        raise InputError(
            "expected columns hz_gon,v_gon,slope_distance_m (or hz_deg,v_deg,...) or "
            f"x_m,y_m,z_m; header is {', '.join(header)}",
            path,
            "line 1",
        )
    ids: list[str] = []
    lines: list[int] = []
    data: list[list[float]] = []
    for line, row in rows:
        if len(row) != len(header):
            raise InputError(
                f"expected {len(header)} fields like the header, got {len(row)}",
                path,
                f"line {line}",
            )
        pid = row[ic]
        if not pid:
            raise InputError("empty point id", path, f"line {line}")

        def get(col: str | None, row: list[str] = row, line: int = line) -> float:
            return math.nan if col is None else _number(row[header.index(col)], col, path, line)

        values = [get(hz_col) * unit, get(v_col) * unit, get(sd_col)]
        values += [get(c) for c in xyz_cols] if xyz_cols else [math.nan] * 3
        ph = get("prism_height_m") if "prism_height_m" in header else 0.0
        values.append(0.0 if math.isnan(ph) else ph)
        if not (
            all(math.isfinite(v) for v in values[:3]) or all(math.isfinite(v) for v in values[3:6])
        ):
            raise InputError(
                f"point {pid!r}: needs Hz, V and slope distance, or x, y, z", path, f"line {line}"
            )
        if math.isfinite(values[2]) and values[2] <= 0:
            raise InputError(
                f"point {pid!r}: slope distance must be positive, got {values[2]}",
                path,
                f"line {line}",
            )
        ids.append(pid)
        lines.append(line)
        data.append(values)
    if not data:
        raise InputError("no observation rows after the header", path)
    a = np.asarray(data, dtype=float)
    return Observations(
        point_ids=tuple(ids),
        hz=a[:, 0],
        v=a[:, 1],
        sd=a[:, 2],
        xyz=a[:, 3:6],
        prism_height=a[:, 6],
        source=str(path),
        lines=tuple(lines),
    )


def read_observations(path: str | Path) -> Observations:
    """Read observations: ``.csv`` as CSV, anything else (``.gsi``, ``.txt``) as Leica GSI."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        return read_observations_csv(path)
    return parse_gsi(_read_text(path, "GSI"), path)


@dataclass(frozen=True, eq=False)
class RobotPoints:
    """Prism positions read from a robot point file.

    Attributes
    ----------
    point_ids
        Ids matched against the observations.
    xyz
        ``(n, 3)`` prism positions in the base frame (metres), or None when the
        file holds joint values.
    joints
        ``(n, dof)`` joint values (radians) from columns ``q1_deg, q2_deg, ...``,
        or None when the file holds positions.
    source
        The file.
    lines
        1-based line of each row.
    """

    point_ids: tuple[str, ...]
    xyz: np.ndarray | None
    joints: np.ndarray | None
    source: str
    lines: tuple[int, ...]


def read_robot_points(path: str | Path) -> RobotPoints:
    """Read a robot point CSV: ``point_id,x_m,y_m,z_m`` or ``point_id,q1_deg,...,qN_deg``."""
    path = Path(path)
    header, rows = _rows(_read_text(path, "robot point"), path)
    ic = _id_column(header, path)
    cols: tuple[str, ...] | None = next(
        (c for c in (("x_m", "y_m", "z_m"), ("x", "y", "z")) if all(k in header for k in c)),
        None,
    )
    joints = cols is None
    if joints:
        k = 1
        while f"q{k}_deg" in header:
            k += 1
        cols = tuple(f"q{j}_deg" for j in range(1, k))
    if not cols:
        raise InputError(
            "expected columns point_id,x_m,y_m,z_m (base frame) or point_id,q1_deg,...,qN_deg "
            f"(joint values); header is {', '.join(header)}",
            path,
            "line 1",
        )
    ids: list[str] = []
    values: list[list[float]] = []
    lines: list[int] = []
    seen: dict[str, int] = {}
    for line, row in rows:
        if len(row) != len(header):
            raise InputError(
                f"expected {len(header)} fields like the header, got {len(row)}",
                path,
                f"line {line}",
            )
        pid = row[ic]
        if pid in seen:
            raise InputError(
                f"point id {pid!r} appears twice (first on line {seen[pid]})",
                path,
                f"line {line}",
            )
        v = [_number(row[header.index(c)], c, path, line) for c in cols]
        if not all(math.isfinite(x) for x in v):
            raise InputError(
                f"point {pid!r}: every one of {', '.join(cols)} is required", path, f"line {line}"
            )
        seen[pid] = line
        ids.append(pid)
        values.append(v)
        lines.append(line)
    if not values:
        raise InputError("no robot points after the header", path)
    a = np.asarray(values, dtype=float)
    return RobotPoints(
        point_ids=tuple(ids),
        xyz=None if joints else a,
        joints=np.radians(a) if joints else None,
        source=str(path),
        lines=tuple(lines),
    )
