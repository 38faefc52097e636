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

Both are UTF-8 CSV files of at most
:data:`~fabflow.positioning.polar.MAX_READINGS_BYTES` bytes and
:data:`~fabflow.positioning.polar.MAX_READINGS` data rows; every value is
checked here (finite, within the bounds of
:func:`~fabflow.positioning.polar.reading_problem` and below) and every problem
is an :class:`~fabflow.errors.InputError` naming the file and the line. How
many readings are matched and adjusted is bounded where they meet the robot
points (:data:`fabflow.positioning.total_station.MAX_PRISM_POINTS`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fabflow.errors import InputError
from fabflow.files import CsvTable, csv_table, show
from fabflow.positioning.gsi import read_gsi
from fabflow.positioning.polar import (
    DEG,
    GON,
    MAX_READINGS,
    MAX_READINGS_BYTES,
    Observations,
    reading_problem,
)

MAX_ROBOT_COORDINATE_M = 100.0
"""Largest magnitude of a prism position in the robot base frame (metres)."""
ID_COLUMNS = ("point_id", "id", "point")


def _table(path: Path, what: str) -> CsvTable:
    table = csv_table(path, what, MAX_READINGS_BYTES, MAX_READINGS, comment="#", lower=True)
    if len(table) == 0:
        raise InputError(f"no data rows after the header of the {what}", path)
    return table


def _ids(table: CsvTable) -> tuple[str, ...]:
    """The stripped point ids; an empty one names its line."""
    name = next((c for c in ID_COLUMNS if c in table.columns), None)
    if name is None:
        raise InputError(
            f"no point id column (expected 'point_id'); header is "
            f"{show(', '.join(table.header), 80)}",
            table.source,
            f"line {table.header_line}",
        )
    ids = tuple(v.strip() for v in table.columns[name])
    empty = next((k for k, v in enumerate(ids) if not v), None)
    if empty is not None:
        raise InputError("empty point id", table.source, table.at(empty))
    return ids


def read_observations_csv(path: str | Path) -> Observations:
    """Read an observation CSV (see the module docstring).

    Raises
    ------
    InputError
        As :func:`~fabflow.files.csv_table`; no angle/distance or coordinate
        columns; a row with neither complete; a value that is not a finite
        number or lies beyond :func:`~fabflow.positioning.polar.reading_problem`'s
        bounds; naming the file and the line.
    """
    path = Path(path)
    table = _table(path, "observation file")
    cols = table.columns
    ids = _ids(table)
    if "hz_gon" in cols and "v_gon" in cols:
        unit, hz_col, v_col = GON, "hz_gon", "v_gon"
    elif "hz_deg" in cols and "v_deg" in cols:
        unit, hz_col, v_col = DEG, "hz_deg", "v_deg"
    else:
        unit, hz_col, v_col = 1.0, None, None
    sd_col = next((c for c in ("slope_distance_m", "sd_m") if c in cols), None)
    xyz_cols = ("x_m", "y_m", "z_m") if all(c in cols for c in ("x_m", "y_m", "z_m")) else None
    if (hz_col is None or sd_col is None) and xyz_cols is None:
        raise InputError(
            "expected columns hz_gon,v_gon,slope_distance_m (or hz_deg,v_deg,...) or "
            f"x_m,y_m,z_m; header is {show(', '.join(table.header), 80)}",
            path,
            f"line {table.header_line}",
        )
    n = len(table)

    def get(col: str | None) -> np.ndarray:
        return np.full(n, np.nan) if col is None else table.numbers(col, allow_empty=True)

    polar = np.column_stack([get(hz_col) * unit, get(v_col) * unit, get(sd_col)])
    xyz = np.column_stack([get(c) for c in xyz_cols]) if xyz_cols else np.full((n, 3), np.nan)
    ph = get("prism_height_m") if "prism_height_m" in cols else np.zeros(n)
    ph = np.where(np.isnan(ph), 0.0, ph)
    complete = np.isfinite(polar).all(axis=1) | np.isfinite(xyz).all(axis=1)
    if not complete.all():
        k = int(np.argmin(complete))
        raise InputError(
            f"point {show(ids[k])}: needs Hz, V and slope distance, or x, y, z",
            path,
            table.at(k),
        )
    obs = Observations(
        point_ids=ids,
        hz=polar[:, 0],
        v=polar[:, 1],
        sd=polar[:, 2],
        xyz=xyz,
        prism_height=ph,
        source=str(path),
        lines=tuple(table.lines.tolist()),
    )
    problem = reading_problem(obs)
    if problem is not None:
        raise InputError(problem[1], path, table.at(problem[0]))
    return obs


def read_observations(path: str | Path) -> Observations:
    """Read observations: ``.csv`` as CSV, anything else (``.gsi``, ``.txt``) as Leica GSI."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        return read_observations_csv(path)
    return read_gsi(path)


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
    header_line
        1-based line of the header.
    """

    point_ids: tuple[str, ...]
    xyz: np.ndarray | None
    joints: np.ndarray | None
    source: str
    lines: tuple[int, ...]
    header_line: int = 1


def read_robot_points(path: str | Path) -> RobotPoints:
    """Read a robot point CSV: ``point_id,x_m,y_m,z_m`` or ``point_id,q1_deg,...,qN_deg``.

    Positions lie within :data:`MAX_ROBOT_COORDINATE_M` of the base; joint
    values are checked against the robot's limits when they are turned into
    positions (:func:`fabflow.robots.prism.prism_points_from_joints`).

    Raises
    ------
    InputError
        As :func:`~fabflow.files.csv_table`; no coordinate or joint columns; a
        duplicate point id; a value that is not a finite number or lies beyond
        the bound; naming the file and the line.
    """
    path = Path(path)
    table = _table(path, "robot point file")
    ids = _ids(table)
    cols: tuple[str, ...] | None = next(
        (c for c in (("x_m", "y_m", "z_m"), ("x", "y", "z")) if all(k in table.columns for k in c)),
        None,
    )
    joints = cols is None
    if joints:
        k = 1
        while f"q{k}_deg" in table.columns:
            k += 1
        cols = tuple(f"q{j}_deg" for j in range(1, k))
    if not cols:
        raise InputError(
            "expected columns point_id,x_m,y_m,z_m (base frame) or point_id,q1_deg,...,qN_deg "
            f"(joint values); header is {show(', '.join(table.header), 80)}",
            path,
            f"line {table.header_line}",
        )
    first: dict[str, int] = {}
    for k, pid in enumerate(ids):
        j = first.setdefault(pid, k)
        if j != k:
            raise InputError(
                f"point id {show(pid)} appears twice (first on line {table.lines[j]})",
                path,
                table.at(k),
            )
    a = np.column_stack([table.numbers(c) for c in cols])
    if not joints:
        far = np.flatnonzero(np.abs(a).max(axis=1) > MAX_ROBOT_COORDINATE_M)
        if far.size:
            raise InputError(
                f"point {show(ids[far[0]])} lies more than {MAX_ROBOT_COORDINATE_M:g} m from "
                "the robot base (are the coordinates in metres, in the base frame?)",
                path,
                table.at(int(far[0])),
            )
    return RobotPoints(
        point_ids=ids,
        xyz=None if joints else a,
        joints=np.radians(a) if joints else None,
        source=str(path),
        lines=tuple(table.lines.tolist()),
        header_line=table.header_line,
    )
