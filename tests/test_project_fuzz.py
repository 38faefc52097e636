"""Fuzzing the project file: mutated example projects through validate and a tiny build.

Every mutation of the example projects (a value replaced by NaN, infinity, a huge
or negative number, zero, a wrong type, a boolean, a deep nesting; a key removed,
misspelt or written twice; a path leading outside or to a device) must end in a
valid project or one :class:`~fabflow.errors.InputError`, never in another
exception; a valid project's JSON is finite. A sample goes through
``fabflow program`` in-process: exit 0 or 2, and no NaN or infinity in any file
written.

The runs here are seeded and sized for CI (1,500 validations and 60 builds, about
40 s). A larger run with a fresh random seed each time (N validations, N / 50
builds): ``FABFLOW_FUZZ_EXAMPLES=20000 pytest tests/test_project_fuzz.py``.
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml
from helpers import DATA, PROJECTS
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from fabflow.cli import app
from fabflow.errors import InputError
from fabflow.project import parse_project

BASES = {
    "cabin": yaml.safe_load((PROJECTS / "cabin" / "project.yaml").read_text()),
    "print_path": yaml.safe_load((PROJECTS / "print_path" / "project.yaml").read_text()),
    "sim": yaml.safe_load((DATA / "sim" / "project.yaml").read_text()),
}
TINY_PRINT = {
    "name": "tiny-print",
    "robot": {
        "model": "abb_irb4600_60_205",
        "platform": {"T_platform_base": {"xyz": [0.7, 0, 0.6]}},
    },
    "localization": {"method": "total_station"},
    "elements": [{"print_path": {"dxf": "sine_wall.dxf", "layers": ["WALL_OUTER"], "n_layers": 2}}],
    "program": {"format": "rapid"},
}
BUILD_BASES = {"sim": BASES["sim"], "tiny_print": TINY_PRINT}

SPECIAL: list[Any] = [
    math.nan, math.inf, -math.inf, 1e308, -1e308, 1e12, 2e9, 0, 0.0, -1, -0.5, 1e-300,
    1e-12, 10**30, -(10**30), 2**63, True, False, None, "", "text", "1e-3", [], {}, [1, 2],
    [[[[1]]]], {"x": 1}, 3.0, 1, 100, 0.5,
]  # fmt: skip
PATHS = [
    "/etc/passwd", "../outside.dxf", "/dev/zero", "missing.dxf", "sine_wall.dxf", ".",
    "sub/../sine_wall.dxf", "link.dxf", "/etc", "~/x.dxf",
]  # fmt: skip
FIELDS: list[tuple[tuple[Any, ...], list[Any]]] = [
    (("elements", 0, "cabin", "block", "height"), [1e-9, 1e-6, 0.001, 10.0]),
    (("elements", 0, "cabin", "block", "length"), [1e-9, 0.16, 100.0, 1e9]),
    (("elements", 0, "cabin", "length"), [1e9, 1e3, 0.5]),
    (("elements", 0, "cabin", "height"), [1e9, 4.3, 3.2]),
    (("elements", 0, "cabin", "robot_parts"), [[], ["Z"], ["A", "A"], ["front"]]),
    (("elements", 0, "cabin", "openings"),
     [[], [{"wall": "left", "center": 1, "width": 1e-9, "height": 1e-9}]]),
    (("elements", 0, "print_path", "n_layers"), [10**9, 0, 1, 3.0, True]),
    (("elements", 0, "print_path", "layer_height"), [100, 1e-9, 1.0]),
    (("elements", 0, "print_path", "speed"), [1e-9, 1e9]),
    (("elements", 0, "print_path", "sample_rate_hz"), [1e9, 1e-9]),
    (("elements", 0, "print_path", "mesh"), ["sine_wall.dxf"]),
    (("elements", 0, "task_points", 0, "layer"), [10**9, -1, 5]),
    (("elements", 0, "task_points", 0, "params"), [{"depth": math.nan}, {"a": True}]),
    (("planning", "candidate_spacing"), [1e-9, 1e-3, 1e9]),
    (("planning", "headings_deg"), [[], [math.nan], [1e9], list(range(500))]),
    (("planning", "lift_step"), [1e-9, 1e9]),
    (("planning", "reach_margin"), [1e9, 5.0]),
    (("planning", "start"), [[1e9, 1e9], [math.inf, 0]]),
    (("site", "extent_max"), [[1e9, 1e9], [-1e9, 0]]),
    (("site", "obstacles"), [[{"polygon": {"points": [[0, 0], [0, 0], [0, 0]]}}],
                             [{"box": {"min": [0, 0, 0], "max": [1e9, 1e9, 1e9]}}]]),
    (("robot", "platform", "footprint"), [[math.inf, 1], [1e-9, 1e-9], [1e9, 1]]),
    (("robot", "platform", "lift"), [[1, 0], [-1e9, 1e9], [0, 0]]),
    (("robot", "platform", "safety_margin"), [1e9, -1]),
    (("robot", "model"), ["ur10e", "brokk_170", "kuka_kr60", "abb_irb4600_60_205"]),
    (("program", "format"), ["krl", "rapid", "urscript", "json", "gcode"]),
    (("program", "speed"), [math.inf, 1e-9, 1e9]),
    (("program", "approach"), [1e9, 1e-9]),
    (("program", "blend"), [1e9, -1]),
    (("localization", "method"), ["uwb", "icp", "total_station"]),
    (("localization", "uwb", "dwell_s"), [1e9, 1e-9]),
    (("localization", "uwb", "rate_hz"), [1e9, 1e-9]),
    (("localization", "uwb", "sigma"), [1e-9, 1e9]),
    (("localization", "uwb", "tags"), [[], [[0, 0, 0]], [[1e9, 0, 0]]]),
    (("localization", "uwb", "anchors"), [{"A": [0, 0, 0], "B": [0, 0, 0], "C": [0, 0, 0]}]),
    (("localization", "total_station", "observations"), PATHS),
    (("localization", "total_station", "n_points"), [3, 50, 51, 4.0]),
    (("localization", "icp", "map"), PATHS),
    (("localization", "integrity", "alpha"), [1e-300, 0.49, 0.5]),
    (("simulation", "runs"), [10**9, 0]),
    (("simulation", "seed"), [-1, 2**64, 10**30]),
    (("simulation", "driving_error"), [1e9, 0]),
    (("limits",), [{"max_elements": 1}, {"max_path_samples": 1}, {"max_candidates": 1}]),
    (("allow_outside_paths",), [True, "yes", 1]),
]  # fmt: skip
TP = ("elements", 0, "task_points", 0)
PP = ("elements", 0, "print_path")
BUILD_FIELDS: list[tuple[tuple[Any, ...], list[Any]]] = [
    (("program", "speed"), [1e-9, 1e-3, 5.0, 1e9]),
    (("program", "approach"), [1e-9, 2.0, 1e3]),
    (("program", "blend"), [0, 0.5, 1e3]),
    ((*TP, "pose", "xyz"), [[1e6, 0, 0], [1.5, 1.0, -100], [1.5, 1.0, 1e9], [0, 0, 0]]),
    ((*TP, "pose", "abc_deg"), [[1e9, 0, 0], [0, 90, 0], [360, 720, -1e9], [0, 0, 0]]),
    ((*TP, "action"), ["drill", "measure"]),
    ((*TP, "params"), [{"depth": 1e9}, {"depth": 0}]),
    (("robot", "platform", "footprint"), [[1e-9, 1e-9], [50, 50]]),
    (("robot", "platform", "lift"), [[0, 0], [-5, 5], [0, 100]]),
    (("robot", "platform", "T_platform_base", "xyz"), [[0, 0, 0], [1e3, 0, 0], [0, 0, -10]]),
    (("robot", "platform", "T_platform_base", "abc_deg"), [[0, 90, 0], [45, 0, 180]]),
    (("robot", "platform", "safety_margin"), [0, 10]),
    (("robot", "tool", "T_flange_tool"), [{"xyz": [0, 0, 5]}, {"abc_deg": [0, 90, 0]}]),
    (("localization", "uwb", "sigma"), [1e-9, 1e3]),
    (("localization", "uwb", "tags"), [[[0, 0, 0]], [[1e3, 0, 0], [0, 0, 0]]]),
    (("localization", "uwb", "dwell_s"), [1e-9, 20.0]),
    (("localization", "uwb", "rate_hz"), [1e-9, 1e3]),
    (("localization", "uwb", "estimator"), ["ls", "wls", "eskf"]),
    (("localization", "uwb", "calibration"), [{"A1": [1e3, 1e-9]}, {"A2": [0, 1e9]}]),
    (("localization", "uwb", "calibration_sigma"), [0, 1e3]),
    (("localization", "uwb", "anchors", "A4"), [[0, 0, 1.0], [1e6, 1e6, 1e6]]),
    (("localization", "method"), ["total_station", "icp"]),
    (("localization", "total_station", "procedure"), ["three_point"]),
    (("localization", "total_station", "distance_sigma_mm"), [1e-9, 1e6]),
    (("localization", "total_station", "three_point_step"), [1e-9, 1e3]),
    (("localization", "total_station", "T_world_instrument", "xyz"), [[1e6, 0, 0], [2, 2, 0]]),
    (("localization", "icp", "voxel_size"), [1e-9, 1e3]),
    (("localization", "icp", "max_correspondence_distance"), [1e-9, 1e3]),
    (("localization", "integrity"), [{"alpha": 1e-9}, {"alpha": 0.49}, {"on_failure": "warn"},
                                     {"parking_sigma": 1e-9}, {"parking_sigma_deg": 1e3}]),
    (("simulation", "driving_error"), [0, 1e3]),
    (("simulation", "driving_heading_error_deg"), [0, 1e6]),
    (("simulation", "robot_repeatability"), [0, 1e3]),
    (("simulation", "seed"), [0, 2**62]),
    (("simulation", "sensor_noise"), [False]),
    (("planning", "headings_deg"), [[0], [1e9, -1e9]]),
    (("planning", "candidate_spacing"), [0.05, 50]),
    (("planning", "lift_step"), [1e-9, 1e9]),
    (("planning", "reach_margin"), [0, 3]),
    (("planning", "max_stations"), [1]),
    (("planning", "start"), [[1e6, 1e6]]),
    (("tolerances", "position"), [1e-9, 1e3]),
    (("tolerances", "rotation_deg"), [1e-9, 1e6]),
    (("site", "obstacles"), [[{"polygon": {"points": [[0, 0], [1, 1], [2, 2]]}}],
                             [{"box": {"min": [1.4, 0.9, 0], "max": [2.0, 1.5, 1]}}]]),
    (("robot", "model"), ["ur10e", "brokk_170", "kuka_kr60_3"]),
    ((*PP, "layer_height"), [1e-3, 0.5]),
    ((*PP, "n_layers"), [1, 40]),
    ((*PP, "speed"), [1e-3, 10]),
    ((*PP, "sample_rate_hz"), [1, 1e4]),
    ((*PP, "origin"), [{"xyz": [1e3, 0, 0]}, {"abc_deg": [0, 90, 0]}, {"xyz": [0, 0, -5]}]),
    ((*PP, "closed"), [False]),
]  # fmt: skip
"""Legal but extreme values for the build sample: they pass validation and reach the stages."""
NON_FINITE = re.compile(r"(?<![\w.])-?(?:nan|inf|infinity)(?![\w])", re.IGNORECASE)


def _nodes(data: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Paths of every node below the top (keys and indices)."""
    out: list[tuple[Any, ...]] = []
    items = (
        data.items()
        if isinstance(data, dict)
        else enumerate(data)
        if isinstance(data, list)
        else []
    )
    for key, value in items:
        out.append((*prefix, key))
        out += _nodes(value, (*prefix, key))
    return out


def _set(data: Any, path: tuple[Any, ...], value: Any) -> None:
    """Set ``value`` at ``path``, making mappings on the way (a list index past the end appends)."""
    for key in path[:-1]:
        if isinstance(data, dict):
            if not isinstance(data.get(key), dict | list):
                data[key] = {}
            data = data[key]
        elif isinstance(data, list) and isinstance(key, int) and key < len(data):
            data = data[key]
        else:
            return
    if isinstance(data, dict):
        data[path[-1]] = value
    elif isinstance(data, list) and isinstance(path[-1], int) and path[-1] < len(data):
        data[path[-1]] = value


def _delete(data: Any, path: tuple[Any, ...]) -> None:
    for key in path[:-1]:
        data = data[key]
    del data[path[-1]]


def _misspell(key: str, i: int) -> str:
    i %= max(len(key), 1)
    return key[:i] + key[i + 1 :] if len(key) > 1 else key + "x"


@st.composite
def mutations(draw: st.DrawFn, data: Any) -> Any:
    """Apply one to three mutations to a copy of ``data``."""
    data = copy.deepcopy(data)
    for _ in range(draw(st.integers(1, 3))):
        nodes = _nodes(data)
        op = draw(
            st.sampled_from(["special", "number", "field", "field", "delete", "misspell", "path"])
        )
        path = draw(st.sampled_from(nodes)) if nodes else ("name",)
        if op == "special":
            _set(data, path, copy.deepcopy(draw(st.sampled_from(SPECIAL))))
        elif op == "number":
            number = st.floats(allow_nan=True, allow_infinity=True) | st.integers(-(10**20), 10**20)
            _set(data, path, draw(number))
        elif op == "field":
            field, values = draw(st.sampled_from(FIELDS))
            _set(data, field, copy.deepcopy(draw(st.sampled_from(values))))
        elif op == "delete":
            _delete(data, path)
        elif op == "misspell" and isinstance(path[-1], str):
            parent = path[:-1]
            holder = data
            for key in parent:
                holder = holder[key]
            holder[_misspell(path[-1], draw(st.integers(0, 20)))] = holder.pop(path[-1])
        elif op == "path":
            _set(data, path, draw(st.sampled_from(PATHS)))
    return data


@st.composite
def build_texts(draw: st.DrawFn) -> str:
    """A build base with one or two legal but extreme values, or a general mutation."""
    if draw(st.integers(0, 3)) == 0:
        return draw(project_texts(BUILD_BASES))
    data = copy.deepcopy(BUILD_BASES[draw(st.sampled_from(sorted(BUILD_BASES)))])
    for _ in range(draw(st.integers(1, 2))):
        field, values = draw(st.sampled_from(BUILD_FIELDS))
        if field[:2] == ("elements", 0) and field[2] not in data["elements"][0]:
            continue
        if field[:2] == ("localization", "uwb") and "uwb" not in data["localization"]:
            continue
        _set(data, field, copy.deepcopy(draw(st.sampled_from(values))))
    data.get("program", {}).pop("format", None)  # the robot's own language
    return yaml.safe_dump(data, sort_keys=False)


@st.composite
def project_texts(draw: st.DrawFn, bases: dict[str, Any]) -> str:
    """YAML text of a mutated base project, sometimes mutated as text too."""
    data = draw(mutations(bases[draw(st.sampled_from(sorted(bases)))]))
    text = yaml.safe_dump(data, sort_keys=False)
    kind = draw(st.sampled_from(["none"] * 6 + ["duplicate", "deep", "truncate", "alias", "junk"]))
    if kind == "duplicate":
        lines = text.splitlines(keepends=True)
        i = draw(st.integers(0, len(lines) - 1))
        text = "".join([*lines[: i + 1], lines[i], *lines[i + 1 :]])
    elif kind == "deep":
        depth = draw(st.sampled_from([10, 70, 5000]))
        text += "description: " + "[" * depth + "]" * depth + "\n"
    elif kind == "truncate":
        text = text[: draw(st.integers(0, len(text)))]
    elif kind == "alias":
        text = (
            "x0: &x0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n"
            + "".join(f"x{i}: &x{i} [{', '.join([f'*x{i - 1}'] * 10)}]\n" for i in range(1, 9))
            + text
        )
    elif kind == "junk":
        i = draw(st.integers(0, len(text)))
        text = (
            text[:i]
            + draw(st.sampled_from(["\t", ": :", "- [", "!!python/object:os.system", "\x00", "{"]))
            + text[i:]
        )
    return text


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A project folder with the drawing, a link out of it, and a file beside it."""
    root = tmp_path_factory.mktemp("fuzz")
    inside = root / "project"
    (inside / "sub").mkdir(parents=True)
    shutil.copy(PROJECTS / "print_path" / "sine_wall.dxf", inside)
    (root / "outside.dxf").write_text("not a drawing\n")
    (inside / "link.dxf").symlink_to("/etc/passwd")
    return inside


def validate_or_input_error(text: str, folder: Path) -> Any:
    """The project, or None after one InputError that echoes no file content."""
    try:
        project = parse_project(text, folder / "project.yaml", folder)
    except InputError as exc:
        message = str(exc)
        assert message and "root:x:0:0" not in message and "not a drawing" not in message
        return None
    json.dumps(project.model_dump(mode="json"), allow_nan=False)
    return project


def _validate_run(folder: Path, examples: int, derandomize: bool = True) -> None:
    @settings(
        max_examples=examples,
        deadline=None,
        derandomize=derandomize,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(text=project_texts(BASES))
    def run(text: str) -> None:
        validate_or_input_error(text, folder)

    run()


LARGE = int(os.environ.get("FABFLOW_FUZZ_EXAMPLES", "0"))
"""With ``FABFLOW_FUZZ_EXAMPLES=N`` the same tests run N validations and N / 50
builds with a fresh random seed each time, instead of CI's seeded sample."""


def test_fuzz_validate(folder: Path) -> None:
    _validate_run(folder, LARGE or 1500, derandomize=not LARGE)


def _reject_constant(token: str) -> float:
    raise AssertionError(f"non-finite number {token} in JSON")


def assert_finite_outputs(out: Path) -> None:
    """No NaN or infinity in any JSON or program file under ``out``."""
    for path in out.rglob("*"):
        if path.suffix == ".json":
            json.loads(path.read_text(), parse_constant=_reject_constant)
        elif path.suffix in (".src", ".dat", ".mod", ".script", ".urscript", ".gcode"):
            text = path.read_text()
            assert not NON_FINITE.search(text), (path.name, NON_FINITE.search(text))


def _build_run(folder: Path, examples: int, derandomize: bool = True) -> None:
    runner = CliRunner()
    counter = iter(range(10**9))

    @settings(
        max_examples=examples,
        deadline=None,
        derandomize=derandomize,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(text=build_texts())
    def run(text: str) -> None:
        work = folder / f"build{next(counter)}"
        work.mkdir()
        shutil.copy(folder / "sine_wall.dxf", work)
        (work / "project.yaml").write_text(text)
        result = runner.invoke(app, ["program", str(work), "-o", str(work / "out")])
        if result.exception is not None and not isinstance(result.exception, SystemExit):
            raise result.exception
        assert result.exit_code in (0, 2), result.output[-2000:]
        if (work / "out").exists():
            assert_finite_outputs(work / "out")
        shutil.rmtree(work)

    run()


def test_fuzz_program_build(folder: Path) -> None:
    _build_run(folder, max(LARGE // 50, 1) if LARGE else 60, derandomize=not LARGE)
