"""Building a preview model from a project, and reading simulation results for it."""

from __future__ import annotations

import csv
import json
import re
from collections import defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from fabflow.design.elements import Element, elements_from_json
from fabflow.design.generate import generate_elements
from fabflow.errors import InputError
from fabflow.positioning.result import BasePose
from fabflow.preview.arm import RobotArm
from fabflow.preview.model import PreviewModel, build_model
from fabflow.project import Project
from fabflow.robots.catalog import get_robot
from fabflow.tasks.plan import Plan
from fabflow.tasks.planner import plan_project
from fabflow.tasks.split import with_pieces

ID_COLUMNS = ("element", "element_id", "id")
"""Column names accepted for the element id in a deviation table."""
DEVIATION_COLUMNS = (
    "deviation_m",
    "deviation",
    "translation_error_m",
    "translation_m",
    "position_error_m",
    "dev_translation_m",
)
"""Column names accepted for the translational deviation (metres) in a deviation table."""


def model_for_project(
    project: Project,
    elements: Sequence[Element] | None = None,
    plan: Plan | None = None,
    sim_dir: str | Path | None = None,
    localization: Mapping[int | str, BasePose] | None = None,
) -> PreviewModel:
    """The preview model of a project: its elements, plan, robot and results.

    Parameters
    ----------
    project
        The validated project.
    elements
        The design's elements; generated from the project if ``None``. Print
        paths that the plan split into per-station pieces are replaced by the
        pieces its work packages name (:func:`fabflow.tasks.split.with_pieces`).
    plan
        The plan; planned from the project if ``None``.
    sim_dir
        A ``fabflow simulate`` output folder (per-element deviations, mean over
        runs, and base poses) or a ``fabflow build`` output folder (its
        ``localization/`` base poses; its ``elements.json`` and ``plan.json``
        are used when neither ``elements`` nor ``plan`` is given).
    localization
        Localization results by work-package index or station id (e.g. from the
        build's ``localize`` stage); they take precedence over ``sim_dir``'s.
    """

    if sim_dir is not None and (elements is None or plan is None):
        built_elements, built_plan = read_build_outputs(sim_dir)
        if elements is None and plan is None and built_plan is not None:
            elements, plan = built_elements, built_plan
    if elements is None:
        elements = generate_elements(project.elements, project.path, project.limits)
    if plan is None:
        plan = plan_project(project, elements)
    elements = with_pieces(elements, plan.split_elements)
    deviation = None
    results: dict[int | str, BasePose] = {}
    if sim_dir is not None:
        deviation = read_deviations(sim_dir, required=False)
        results.update(read_base_poses(sim_dir))
        if deviation is None and not results:
            raise InputError(
                "holds neither a per-element deviation table (CSV with columns "
                f"{' or '.join(ID_COLUMNS)} and {' or '.join(DEVIATION_COLUMNS)}) "
                "nor base pose JSON files",
                source=sim_dir,
            )
    results.update(localization or {})
    check_results_match_plan(results, plan)
    T_flange_tool = project.robot.tool.T_flange_tool.matrix()
    return build_model(
        elements,
        plan,
        name=project.name,
        platform=project.robot.platform,
        T_flange_tool=T_flange_tool,
        arm=RobotArm(get_robot(project.robot.name), T_flange_tool),
        deviation=deviation,
        tolerance=project.tolerances.position,
        localization=results,
        method=project.localization.method,
    )


def read_build_outputs(folder: str | Path) -> tuple[list[Element] | None, Plan | None]:
    """The elements and plan a ``fabflow build`` wrote (``elements.json``, ``plan.json``).

    Either is ``None`` when its file is absent (e.g. a ``fabflow simulate``
    folder). Localization results in the same folder are numbered by the visits
    of this plan, so the preview uses it instead of planning again.

    Raises
    ------
    InputError
        If a file is present but malformed.
    """

    folder = Path(folder)
    elements = plan = None
    path = folder / "elements.json"
    try:
        if path.is_file():
            data = json.loads(path.read_text(encoding="utf-8"))
            elements = elements_from_json(data["elements"] if isinstance(data, dict) else data)
        path = folder / "plan.json"
        if path.is_file():
            plan = Plan.from_dict(json.loads(path.read_text(encoding="utf-8")))
    except (
        OSError,
        UnicodeDecodeError,
        json.JSONDecodeError,
        KeyError,
        TypeError,
        ValueError,
    ) as exc:
        raise InputError(f"cannot read build output: {exc}", source=path) from None
    return elements, plan


def check_results_match_plan(results: Mapping[int | str, BasePose], plan: Plan) -> None:
    """Check that per-visit localization results belong to this plan's visits.

    Raises
    ------
    InputError
        If a result is numbered for a visit the plan does not have, or was made
        at another station than the plan's visit of that number.
    """
    packages = plan.work_packages
    for key, result in results.items():
        if not isinstance(key, int):
            continue
        if key >= len(packages) or packages[key].station.id != result.station:
            planned = packages[key].station.id if key < len(packages) else "no such visit"
            raise InputError(
                f"the localization result of visit {key + 1} is for station {result.station}, "
                f"but the plan has {planned}: the results were made for another plan "
                "(re-run fabflow build or simulate, or pass the build folder with its plan.json)"
            )


def _deviation_table(path: Path) -> dict[str, list[float]] | None:
    """Deviations by element id from one CSV file, or ``None`` if it is not such a table."""
    with path.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        fields = [c.strip() for c in (reader.fieldnames or [])]
        id_col = next((c for c in ID_COLUMNS if c in fields), None)
        dev_col = next((c for c in DEVIATION_COLUMNS if c in fields), None)
        if id_col is None or dev_col is None:
            return None
        values: dict[str, list[float]] = defaultdict(list)
        for line, row in enumerate(reader, start=2):
            row = {k.strip(): v for k, v in row.items() if k is not None}
            try:
                values[row[id_col].strip()].append(float(row[dev_col]))
            except (TypeError, ValueError):
                raise InputError(
                    f"column '{dev_col}' must hold a number in metres, got {row.get(dev_col)!r}",
                    source=path,
                    location=f"line {line}",
                ) from None
    return values


def read_deviations(sim_dir: str | Path, required: bool = True) -> dict[str, float] | None:
    """Mean simulated deviation (metres) per element id from a simulation output folder.

    Every CSV file in the folder (not its subfolders) with an element id column
    (one of :data:`ID_COLUMNS`) and a deviation column (one of
    :data:`DEVIATION_COLUMNS`) is read; rows of the same element (one per run)
    are averaged.

    Parameters
    ----------
    sim_dir
        The folder.
    required
        Raise if the folder holds no such table; otherwise return ``None``.

    Raises
    ------
    InputError
        If the folder does not exist, or (``required``) holds no such table.
    """
    folder = Path(sim_dir)
    if not folder.is_dir():
        raise InputError("results folder does not exist", source=folder)
    values: dict[str, list[float]] = defaultdict(list)
    found = False
    for path in sorted(folder.glob("*.csv")):
        table = _deviation_table(path)
        if table is None:
            continue
        found = True
        for eid, v in table.items():
            values[eid].extend(v)
    if not found and not required:
        return None
    if not found:
        raise InputError(
            "no per-element deviation table found: expected a CSV with columns "
            f"{' or '.join(ID_COLUMNS)} and {' or '.join(DEVIATION_COLUMNS)}",
            source=folder,
        )
    return {eid: float(np.mean(v)) for eid, v in values.items()}


def read_base_poses(folder: str | Path) -> dict[int | str, BasePose]:
    """Localization results in a folder tree, by visit index or station id.

    A file counts when it is a JSON object with ``T_world_base``, ``method`` and
    ``station`` (the base pose JSON of ``fabflow localize``); other JSON files
    are ignored. A file named ``visit_NN_...json`` (as ``fabflow simulate``
    writes them, NN counted from 1) is the result of work package ``NN - 1``;
    any other is its station's result.
    """
    out: dict[int | str, BasePose] = {}
    for path in sorted(Path(folder).rglob("*.json")):
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            continue
        if not isinstance(data, dict) or not {"T_world_base", "method"} <= data.keys():
            continue
        if not data.get("station"):
            continue
        try:
            result = BasePose.from_dict(data)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"malformed base pose: {exc}", source=path) from None
        visit = re.match(r"visit_(\d+)_", path.name)
        out[int(visit.group(1)) - 1 if visit else str(result.station)] = result
    return out
