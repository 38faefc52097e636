"""Reading what ``fabflow export`` exports: a build output folder and simulated as-built poses.

A ``fabflow build`` folder holds ``elements.json`` (required), ``plan.json``
(absent for a stone wall, which has no plan), ``project.json`` (the platform's
footprint) and, depending on the localization, ``uwb_anchors.json`` or
``instrument_setups.json``. A ``fabflow simulate`` folder holds
``asbuilt_run0.csv``: the planned and as-built pose of every element in run 0
(x, y, z in metres, KUKA A, B, C in degrees).

Each file is read through fabflow's own readers (:meth:`Element.from_dict`,
:meth:`Plan.from_dict`) and checked: anything malformed (not JSON, a missing
field, a number that is not finite, a plan naming elements the folder does not
hold) is an :class:`~fabflow.errors.InputError` naming the file and where in it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_args

import numpy as np

from fabflow.design.elements import Element, ElementType, elements_from_json
from fabflow.errors import InputError
from fabflow.files import csv_table, read_text, strict_json
from fabflow.tasks.plan import Plan
from fabflow.tasks.split import with_pieces
from fabflow.transforms.so3 import matrix_from_abc

MAX_BUILD_FILE_BYTES = 2**29
"""Largest build output file read (bytes): a long print's elements.json is large."""
MAX_ASBUILT_ROWS = 1_000_000
"""Most rows of an as-built table read."""
ASBUILT_FILE = "asbuilt_run0.csv"
ASBUILT_COLUMNS = ("x_m", "y_m", "z_m", "a_deg", "b_deg", "c_deg")
"""The as-built pose columns (each prefixed ``asbuilt_``)."""
_ERRORS = (KeyError, TypeError, ValueError, AttributeError, IndexError)


@dataclass(frozen=True, eq=False)
class BuildFolder:
    """What a build output folder holds for an export.

    Attributes
    ----------
    folder
        The folder.
    elements
        Its elements (world frame, metres), print paths the plan split replaced
        by their pieces.
    plan
        Its plan, ``None`` when it has none.
    footprint
        The platform's footprint (length, width) in metres; ``None`` without a plan.
    anchors, setups
        UWB anchors and total station set-ups: id -> ``(3,)`` position (world, metres).
    files
        The files read.
    """

    folder: Path
    elements: list[Element]
    plan: Plan | None = None
    footprint: tuple[float, float] | None = None
    anchors: dict[str, np.ndarray] = field(default_factory=dict)
    setups: dict[str, np.ndarray] = field(default_factory=dict)
    files: tuple[Path, ...] = ()


def read_json(path: Path, what: str) -> Any:
    """A JSON file of a build (no NaN or infinity), or an InputError naming it."""
    text = read_text(path, what, MAX_BUILD_FILE_BYTES)
    try:
        return strict_json(text)
    except ValueError as exc:
        line = getattr(exc, "lineno", None)
        raise InputError(
            f"{what} is not valid JSON: {getattr(exc, 'msg', exc)}",
            path,
            f"line {line}" if line else None,
        ) from None


def _check_units(data: dict[str, Any], path: Path) -> None:
    if data.get("units", "m") != "m" or data.get("frame", "world") != "world":
        raise InputError("expected units 'm' and frame 'world'", path)


def _check_elements(elements: list[Element], path: Path, key: str) -> None:
    """Refuse non-finite or non-4x4 poses and geometry, and ids used twice."""
    seen: set[str] = set()
    for k, e in enumerate(elements):
        where = f"{key}[{k}] ({e.id})"
        T = np.asarray(e.T_world_element)
        if not e.id or e.id in seen:
            raise InputError("an element id is empty or used twice", path, where)
        seen.add(e.id)
        if e.type not in get_args(ElementType):
            raise InputError(f"unknown element type {e.type!r}", path, where)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise InputError("T_world_element must be 4x4 finite numbers", path, where)
        for name, value in (("extents", e.extents), ("polyline", e.polyline)):
            if value is not None and not np.isfinite(value).all():
                raise InputError(f"{name} must be finite numbers", path, where)
        if e.extents is not None and (e.extents.shape != (3,) or (e.extents <= 0).any()):
            raise InputError("extents must be 3 positive sizes (metres)", path, where)


def read_elements(path: Path) -> list[Element]:
    """The elements of ``elements.json`` (as ``fabflow build`` writes it), checked."""
    data = read_json(path, "elements file")
    if isinstance(data, dict):
        _check_units(data, path)
        data = data.get("elements")
    if not isinstance(data, list):
        raise InputError("expected an object with an 'elements' list", path)
    elements = []
    for k, d in enumerate(data):
        try:
            elements.append(elements_from_json([d])[0])
        except _ERRORS as exc:
            raise InputError(f"not an element: {_reason(exc)}", path, f"elements[{k}]") from None
    _check_elements(elements, path, "elements")
    return elements


def _reason(exc: Exception) -> str:
    return f"missing field {exc}" if isinstance(exc, KeyError) else str(exc)


def read_plan(path: Path, elements: list[Element]) -> tuple[Plan, list[Element]]:
    """The plan of ``plan.json`` and the elements with its split pieces, checked.

    Raises
    ------
    InputError
        For a file that is not a plan, a pose that is not finite, or a work
        package naming an element the elements do not hold (a plan of another
        design).
    """
    data = read_json(path, "plan file")
    if not isinstance(data, dict):
        raise InputError("expected a plan object with 'work_packages'", path)
    _check_units(data, path)
    try:
        plan = Plan.from_dict(data)
    except _ERRORS as exc:
        raise InputError(f"not a fabflow plan: {_reason(exc)}", path) from None
    _check_elements(list(plan.split_elements), path, "split_elements")
    try:
        elements = with_pieces(elements, plan.split_elements)
    except _ERRORS as exc:
        raise InputError(f"split_elements: {_reason(exc)}", path) from None
    known = {e.id for e in elements}
    for k, wp in enumerate(plan.work_packages):
        where = f"work_packages[{k}]"
        T = wp.station.T_world_platform
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise InputError("station.T_world_platform must be 4x4 finite numbers", path, where)
        missing = next((eid for eid in wp.elements if eid not in known), None)
        if missing is not None:
            raise InputError(
                f"builds element {missing!r}, which elements.json does not hold: "
                "the plan and the elements come from different builds",
                path,
                where,
            )
    return plan, elements


def read_footprint(path: Path) -> tuple[float, float]:
    """The platform footprint (length, width; metres) of a build's ``project.json``."""
    data = read_json(path, "project file")
    try:
        value = data["project"]["robot"]["platform"]["footprint"]
        length, width = (float(v) for v in value)
    except _ERRORS:
        raise InputError(
            "expected project.robot.platform.footprint: [length, width] in metres", path
        ) from None
    if not (np.isfinite([length, width]).all() and length > 0 and width > 0):
        raise InputError("project.robot.platform.footprint must be positive (metres)", path)
    return length, width


def _position(value: Any, path: Path, where: str) -> np.ndarray:
    try:
        p = np.asarray(value, dtype=float)
    except _ERRORS:
        p = np.zeros(0)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise InputError("expected a position [x, y, z] of finite numbers (metres)", path, where)
    return p


def read_anchors(path: Path) -> dict[str, np.ndarray]:
    """The anchors of a build's ``uwb_anchors.json``: id -> position (world, metres)."""
    data = read_json(path, "anchors file")
    if not isinstance(data, dict) or not isinstance(data.get("anchors"), dict):
        raise InputError("expected an object with an 'anchors' object", path)
    _check_units(data, path)
    return {str(k): _position(v, path, f"anchors.{k}") for k, v in data["anchors"].items()}


def read_setups(path: Path) -> dict[str, np.ndarray]:
    """The set-ups of a build's ``instrument_setups.json``: id -> position (world, metres)."""
    data = read_json(path, "set-ups file")
    if not isinstance(data, dict) or not isinstance(data.get("setups"), list):
        raise InputError("expected an object with a 'setups' list", path)
    _check_units(data, path)
    out = {}
    for k, s in enumerate(data["setups"]):
        if not isinstance(s, dict) or not isinstance(s.get("id"), str):
            raise InputError("expected a set-up with an 'id'", path, f"setups[{k}]")
        out[s["id"]] = _position(s.get("position"), path, f"setups[{k}].position")
    return out


def read_build_folder(folder: str | Path) -> BuildFolder:
    """Read and check what a ``fabflow build`` output folder holds for an export.

    Raises
    ------
    InputError
        When the folder does not exist, has no ``elements.json``, or any of its
        files is malformed (naming the file); when it has a plan with stations
        but no ``project.json`` (the platform footprint comes from it).
    """
    folder = Path(folder)
    if not folder.is_dir():
        what = "is not a folder" if folder.exists() else "does not exist"
        raise InputError(f"build output folder {what}", folder)
    path = folder / "elements.json"
    if not path.exists():
        raise InputError(
            "has no elements.json: expected a fabflow build output folder "
            "(fabflow build PROJECT -o FOLDER)",
            folder,
        )
    files = [path]
    elements = read_elements(path)
    plan = footprint = None
    if (folder / "plan.json").exists():
        files.append(folder / "plan.json")
        plan, elements = read_plan(folder / "plan.json", elements)
    if plan is not None and plan.work_packages:
        path = folder / "project.json"
        if not path.exists():
            raise InputError(
                "is missing: the stations' platform footprint comes from it "
                "(export a complete fabflow build output folder)",
                path,
            )
        files.append(path)
        footprint = read_footprint(path)
    anchors: dict[str, np.ndarray] = {}
    setups: dict[str, np.ndarray] = {}
    if (folder / "uwb_anchors.json").exists():
        files.append(folder / "uwb_anchors.json")
        anchors = read_anchors(folder / "uwb_anchors.json")
    if (folder / "instrument_setups.json").exists():
        files.append(folder / "instrument_setups.json")
        setups = read_setups(folder / "instrument_setups.json")
    return BuildFolder(folder, elements, plan, footprint, anchors, setups, tuple(files))


def asbuilt_file(path: str | Path) -> Path:
    """The as-built table of a ``fabflow simulate`` folder (or the table itself).

    A folder holding :data:`ASBUILT_FILE` gives it; one that does not but has one
    method folder holding it (``OUT/<method>/``) gives that one.

    Raises
    ------
    InputError
        When there is no such table, or several methods' (naming them).
    """
    path = Path(path)
    if not path.is_dir():
        if not path.exists():
            raise InputError("simulation output does not exist", path)
        return path
    if (path / ASBUILT_FILE).exists():
        return path / ASBUILT_FILE
    found = sorted(path.glob(f"*/{ASBUILT_FILE}"))
    if len(found) == 1:
        return found[0]
    if found:
        methods = ", ".join(p.parent.name for p in found)
        raise InputError(
            f"holds as-built poses of several methods ({methods}): pass one method's folder",
            path,
        )
    raise InputError(f"has no {ASBUILT_FILE}: expected a fabflow simulate output folder", path)


def read_asbuilt(path: str | Path) -> dict[str, np.ndarray]:
    """Simulated as-built poses (4x4, world, metres) by element id, from ``asbuilt_run0.csv``.

    Raises
    ------
    InputError
        For a missing column, a value that is not a finite number, or an element
        id given twice (naming the line).
    """
    path = Path(path)
    columns = [f"asbuilt_{c}" for c in ASBUILT_COLUMNS]
    table = csv_table(path, "as-built table", MAX_BUILD_FILE_BYTES, MAX_ASBUILT_ROWS)
    missing = [c for c in ["element", *columns] if c not in table.header]
    if missing:
        raise InputError(
            f"has no column {missing[0]!r}: expected fabflow simulate's {ASBUILT_FILE}",
            path,
            f"line {table.header_line}",
        )
    x, y, z, a, b, c = (table.numbers(col) for col in columns)
    T = np.tile(np.eye(4), (len(table), 1, 1))
    T[:, :3, :3] = matrix_from_abc(np.radians(a), np.radians(b), np.radians(c))
    T[:, :3, 3] = np.column_stack([x, y, z])
    out: dict[str, np.ndarray] = {}
    for k, eid in enumerate(table.columns["element"]):
        eid = eid.strip()
        if not eid or eid in out:
            raise InputError(f"element id {eid!r} is empty or given twice", path, table.at(k))
        out[eid] = T[k]
    return out
