"""The project file: loading, validation messages, JSON schema."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import yaml
from helpers import PROJECTS, ROOT

from fabflow.errors import InputError
from fabflow.project import format_loc, load_project, parse_project, project_json_schema
from fabflow.schema import PoseSpec

BAD = ROOT / "tests" / "data" / "bad_projects"


@pytest.mark.parametrize("name", ["cabin", "print_path"])
def test_example_projects_validate(name: str) -> None:
    project = load_project(PROJECTS / name / "project.yaml")
    assert project.name == name
    assert project.path == (PROJECTS / name / "project.yaml").resolve()


def test_folder_resolves_to_project_yaml() -> None:
    assert load_project(PROJECTS / "cabin").name == "cabin"


def test_relative_paths_resolve_against_project_folder() -> None:
    project = load_project(PROJECTS / "print_path")
    dxf = project.elements[0].print_path.dxf
    assert dxf is not None and dxf.is_absolute() and dxf.exists()
    assert dxf.parent == (PROJECTS / "print_path").resolve()


# (file, field path expected in the message, words expected in the message)
BAD_CASES = [
    ("wrong_type.yaml", "line 6: elements[0].cabin.block.length", "valid number"),
    ("missing_field.yaml", "name", "required field is missing"),
    ("unknown_key.yaml", "line 4: robot.colour", "unknown key"),
    ("missing_path.yaml", "line 4: elements[0].print_path.dxf", "does not exist"),
    ("bad_yaml.yaml", "line 4", "YAML does not parse"),
    ("bad_choice.yaml", "line 3: localization.method", "'uwb', 'total_station' or 'icp'"),
    ("uwb_without_section.yaml", "localization", "needs a 'uwb' section"),
]


@pytest.mark.parametrize(("name", "where", "what"), BAD_CASES)
def test_bad_project_messages(name: str, where: str, what: str) -> None:
    with pytest.raises(InputError) as info:
        load_project(BAD / name)
    message = str(info.value)
    assert name in message
    assert where in message
    assert what in message


def test_every_error_is_listed() -> None:
    text = "name: x\nsite: {extent_min: [0, 0], extent_max: [1, 1], colour: red}\nelements: []\n"
    with pytest.raises(InputError) as info:
        parse_project(text, source="p.yaml")
    message = str(info.value)
    assert "site.colour" in message
    assert "elements" in message and "at least 1" in message


def test_top_level_must_be_mapping() -> None:
    with pytest.raises(InputError, match="mapping"):
        parse_project("- a\n- b\n", source="list.yaml")


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="does not exist"):
        load_project(tmp_path / "nope.yaml")


def test_inconsistent_values_rejected() -> None:
    text = "name: x\nrobot: {platform: {lift: [1.0, 0.5]}}\nelements: [{cabin: {}}]\n"
    with pytest.raises(InputError, match=r"robot\.platform.*min <= max"):
        parse_project(text)
    text = "name: x\nelements: [{cabin: {}, task_points: []}]\n"
    with pytest.raises(InputError, match="exactly one"):
        parse_project(text)


def test_format_loc() -> None:
    assert format_loc(("elements", 2, "cabin", "block", "length")) == (
        "elements[2].cabin.block.length"
    )
    assert format_loc(()) == "(top level)"


def test_pose_spec_matrix_is_kuka_abc() -> None:
    T = PoseSpec(xyz=(1.0, 2.0, 3.0), abc_deg=(90.0, 0.0, 0.0)).matrix()
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    T = PoseSpec(abc_deg=(0.0, 90.0, 0.0)).matrix()
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    T = PoseSpec(abc_deg=(30.0, 20.0, 10.0)).matrix()
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)


def test_json_schema_is_valid_and_accepts_examples() -> None:
    schema = project_json_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    validator = jsonschema.Draft202012Validator(schema)
    for name in ("cabin", "print_path"):
        data = yaml.safe_load((PROJECTS / name / "project.yaml").read_text())
        errors = list(validator.iter_errors(data))
        assert errors == [], errors
    assert list(validator.iter_errors({"name": "x", "elements": [{"cabin": {"bogus": 1}}]}))
    json.dumps(schema)


# ---------------------------------------------------------------- hardening (issue 17)

SMALL = "name: x\nelements: [{cabin: {}}]\n"


def _error(text: str, base_dir: Path | None = None) -> str:
    with pytest.raises(InputError) as info:
        parse_project(text, source="p.yaml", base_dir=base_dir)
    return str(info.value)


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ("name: x\nelements: [{cabin: {length: .inf}}]\n", "line 2: elements[0].cabin.length"),
        ("name: x\nelements: [{cabin: {height: -.inf}}]\n", "line 2: elements[0].cabin.height"),
        ("name: x\nelements: [{cabin: {origin: [.nan, 0, 0]}}]\n", "elements[0].cabin.origin[0]"),
        ("name: x\nelements: [{cabin: {heading_deg: .nan}}]\n", "elements[0].cabin.heading_deg"),
        ("name: x\nrobot: {platform: {footprint: [.inf, 1]}}\nelements: [{cabin: {}}]\n",
         "line 2: robot.platform.footprint[0]"),
        ("name: x\nprogram: {speed: .inf}\nelements: [{cabin: {}}]\n", "line 2: program.speed"),
        ("name: x\nplanning: {headings_deg: [0, .nan]}\nelements: [{cabin: {}}]\n",
         "planning.headings_deg[1]"),
        ("name: x\nelements: [{task_points: [{id: a, pose: {}, params: {d: .nan}}]}]\n",
         "elements[0].task_points[0].params.d"),
        ("name: x\nlocalization: {method: uwb, uwb: {anchors: {A: [0, 0, .nan], B: [1, 0, 0], "
         "C: [0, 1, 0]}}}\nelements: [{cabin: {}}]\n", "localization.uwb.anchors.A[2]"),
        ("name: x\nelements: [{cabin: {length: 1.0e300}}]\n", "elements[0].cabin.length"),
    ],
)  # fmt: skip
def test_non_finite_and_huge_numbers_are_refused_with_field_and_line(text: str, where: str) -> None:
    message = _error(text)
    assert where in message
    assert "finite" in message or "less than or equal" in message


@pytest.mark.parametrize(
    ("section", "where"),
    [
        ("localization: {method: uwb, uwb: {sigma: -0.05, anchors: {A: [0, 0, 0], B: [1, 0, 0], "
         "C: [0, 1, 0]}}}", "localization.uwb.sigma"),
        ("simulation: {driving_error: -0.1}", "simulation.driving_error"),
        ("localization: {total_station: {setup_sigma_mm: -1}}",
         "localization.total_station.setup_sigma_mm"),
        ("robot: {platform: {footprint: [0, 1]}}", "robot.platform.footprint"),
        ("localization: {icp: {min_fitness: 1.5}}", "localization.icp.min_fitness"),
        ("site: {obstacles: [{polygon: {points: [[0, 0], [1, 0], [0, 1]], z_min: 2, z_max: 1}}]}",
         "site.obstacles[0].polygon"),
        ("simulation: {seed: -1}", "simulation.seed"),
    ],
)  # fmt: skip
def test_physical_bounds(section: str, where: str) -> None:
    assert where in _error(f"name: x\n{section}\nelements: [{{cabin: {{}}}}]\n")


@pytest.mark.parametrize(
    ("value", "where"),
    [
        ("{dxf: w.dxf, n_layers: true}", "n_layers"),
        ("{dxf: w.dxf, n_layers: 3.0}", "n_layers"),
        ("{dxf: w.dxf, closed: 1}", "closed"),
        ("{dxf: w.dxf, speed: true}", "speed"),
        ("{dxf: w.dxf, speed: '0.1'}", "speed"),
    ],
)
def test_counts_switches_and_numbers_are_strict(tmp_path: Path, value: str, where: str) -> None:
    (tmp_path / "w.dxf").write_text("0\nEOF\n")
    message = _error(f"name: x\nelements: [{{print_path: {value}}}]\n", tmp_path)
    assert f"elements[0].print_path.{where}" in message


def test_exponent_numbers_are_numbers() -> None:
    text = (
        "name: x\nlocalization: {method: uwb, uwb: {sigma: 5e-2, "
        "anchors: {A: [0, 0, 0], B: [1, 0, 0], C: [0, 1, 1E0]}}}\nelements: [{cabin: {}}]\n"
    )
    p = parse_project(text)
    assert p.localization.uwb is not None and p.localization.uwb.sigma == 0.05


def test_duplicate_keys_are_refused_with_the_line_of_the_second() -> None:
    message = _error("name: x\nelements: [{cabin: {}}]\nname: y\n")
    assert "line 3" in message and "duplicate key 'name'" in message and "line 1" in message
    message = _error("name: x\nelements: [{cabin: {length: 4, width: 3, length: 5}}]\n")
    assert "duplicate key 'length'" in message


def test_deep_nesting_and_alias_bombs_are_refused_fast() -> None:
    t0 = time.perf_counter()
    deep = "name: x\nelements: " + "[" * 5000 + "]" * 5000 + "\n"
    assert "nest deeper than" in _error(deep)
    bomb = "x0: &x0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n" + "".join(
        f"x{i}: &x{i} [{', '.join([f'*x{i - 1}'] * 10)}]\n" for i in range(1, 9)
    )
    assert "through aliases" in _error(bomb)
    assert "the collection it is in" in _error("name: &n [1, *n]\n")
    assert time.perf_counter() - t0 < 5


def test_project_file_must_be_a_bounded_regular_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not a regular file"):
        load_project("/dev/zero")
    big = tmp_path / "project.yaml"
    big.write_text("name: x\ndescription: '" + "x" * (5 * 2**20) + "'\n")
    with pytest.raises(InputError, match="MiB"):
        load_project(tmp_path)
    (tmp_path / "project.yaml").write_bytes(b"name: \xff\n")
    with pytest.raises(InputError, match="not UTF-8"):
        load_project(tmp_path)


@pytest.mark.parametrize(
    ("text", "near"),
    [
        ("name: x\nrobot: {modle: ur10e}\nelements: [{cabin: {}}]\n", "'model'"),
        ("name: x\nplaning: {}\nelements: [{cabin: {}}]\n", "'planning'"),
        ("name: x\nelements: [{cabin: {lenght: 4}}]\n", "'length'"),
        ("name: x\nelements: [{cabin: {block: {heigth: 0.1}}}]\n", "'height'"),
        ("name: x\nlimits: {max_element: 5}\nelements: [{cabin: {}}]\n", "'max_elements'"),
    ],
)
def test_unknown_key_suggests_the_near_name(text: str, near: str) -> None:
    message = _error(text)
    assert f"did you mean {near}?" in message
    assert "did you mean" not in _error("name: x\nzzzzzz: 1\nelements: [{cabin: {}}]\n")


@pytest.mark.parametrize(
    ("text", "where", "limit"),
    [
        ("elements: [{print_path: {dxf: w.dxf, n_layers: 1000000000}}]",
         "elements[0].print_path", "limits.max_elements"),
        ("elements: [{cabin: {block: {height: 1.0e-9}}}]", "elements[0].cabin",
         "limits.max_elements"),
        ("elements: [{task_points: [{id: a, pose: {}}]}]\nplanning: {candidate_spacing: 1.0e-6}",
         "planning.candidate_spacing", "limits.max_candidates"),
        ("elements: [{cabin: {}}]\nlocalization: {method: uwb, uwb: {dwell_s: 1.0e9, "
         "anchors: {A: [0, 0, 0], B: [1, 0, 0], C: [0, 1, 0]}}}",
         "localization.uwb.dwell_s", "limits.max_sensor_samples"),
        ("elements: [{cabin: {}}]\nsimulation: {runs: 1000000000}", "simulation.runs",
         "limits.max_runs"),
    ],
)  # fmt: skip
def test_work_beyond_the_limits_is_refused_fast(
    tmp_path: Path, text: str, where: str, limit: str
) -> None:
    (tmp_path / "w.dxf").write_text("0\nEOF\n")
    t0 = time.perf_counter()
    message = _error(f"name: x\n{text}\n", tmp_path)
    assert time.perf_counter() - t0 < 1
    assert where in message and limit in message
    assert "line " in message


def test_limits_can_be_raised() -> None:
    text = "name: x\nelements: [{cabin: {}}]\n"
    assert "max_elements" in _error(text + "limits: {max_elements: 100}\n")
    p = parse_project(text + "simulation: {runs: 200000}\nlimits: {max_runs: 300000}\n")
    assert p.simulation.runs == 200000 and p.limits.max_runs == 300000


def test_robot_parts_must_name_parts() -> None:
    message = _error("name: x\nelements: [{cabin: {robot_parts: [Z]}}]\n")
    assert "elements[0].cabin" in message and "'Z'" in message
    parse_project("name: x\nelements: [{cabin: {robot_parts: []}}]\n")


def test_vendor_format_suggests_the_robots_own_format() -> None:
    message = _error(
        "name: x\nrobot: {model: abb_irb4600_60_205}\nprogram: {format: krl}\n"
        "elements: [{cabin: {}}]\n"
    )
    assert "line 3: program.format" in message and "'rapid' or 'json'" in message
    message = _error(
        "name: x\nrobot: {model: brokk_170}\nprogram: {format: krl}\nelements: [{cabin: {}}]\n"
    )
    assert "use format 'json'" in message


def test_home_tool_load_lift_axis_and_controller_are_checked() -> None:
    cabin = "elements: [{cabin: {}}]\n"
    message = _error(f"name: x\nrobot: {{home_deg: [0, -90, 90, 0, 0]}}\n{cabin}")
    assert "line 2: robot.home_deg: kuka_kr60_3 has 6 axes, got 5" in message
    message = _error(f"name: x\nrobot: {{home_deg: [0, -90, 170, 0, 0, 0]}}\n{cabin}")
    assert "robot.home_deg: outside the joint limits: axis 3: 170 not in [-120, 158]" in message
    message = _error(f"name: x\nrobot: {{model: ur10e, tool: {{mass: 20}}}}\n{cabin}")
    assert "robot.tool.mass: 20 kg exceeds the ur10e's rated payload of 12.5 kg" in message
    assert "robot.tool.mass" in _error(f"name: x\nrobot: {{tool: {{mass: 0}}}}\n{cabin}")
    assert "lift_axis" in _error(f"name: x\nrobot: {{platform: {{lift_axis: A7}}}}\n{cabin}")
    message = _error(f"name: x\nprogram: {{controller: irc5}}\n{cabin}")
    assert "program.controller: 'irc5' (IRC5 / RobotWare 6) is not a controller" in message
    assert "module_motions" in _error(f"name: x\nprogram: {{module_motions: 5}}\n{cabin}")
    p = parse_project(
        "name: x\nrobot: {home_deg: [0, -90, 90, 0, 30, 0], tool: {mass: 12.5, cog: [0, 0, 0.1]},"
        f" platform: {{lift_axis: E1}}}}\nprogram: {{controller: krc5}}\n{cabin}"
    )
    assert p.robot.home_deg == (0, -90, 90, 0, 30, 0) and p.robot.platform.lift_axis == "E1"
    assert p.robot.tool.mass == 12.5 and p.program.controller == "krc5"


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    """A project folder with a drawing, a file beside the folder and a link out of it."""
    inside = tmp_path / "project"
    inside.mkdir()
    shutil.copy(PROJECTS / "print_path" / "sine_wall.dxf", inside)
    shutil.copy(PROJECTS / "print_path" / "sine_wall.dxf", tmp_path / "outside.dxf")
    (inside / "link.dxf").symlink_to(tmp_path / "outside.dxf")
    return inside


def _print_path(dxf: str, extra: str = "") -> str:
    return f"name: x\n{extra}elements: [{{print_path: {{dxf: '{dxf}', layers: [WALL_OUTER]}}}}]\n"


@pytest.mark.parametrize(
    ("dxf", "why"),
    [
        ("../outside.dxf", "outside the project folder"),
        ("link.dxf", "outside the project folder"),
        ("OUTSIDE", "absolute path"),
        ("/dev/zero", "absolute path"),
    ],
)
def test_paths_stay_in_the_project_folder(folder: Path, dxf: str, why: str) -> None:
    dxf = str(folder.parent / "outside.dxf") if dxf == "OUTSIDE" else dxf
    message = _error(_print_path(dxf), folder)
    assert "line 2: elements[0].print_path.dxf" in message and why in message
    allowed = _print_path(dxf, "allow_outside_paths: true\n")
    if dxf == "/dev/zero":
        assert "not a regular file" in _error(allowed, folder)
    else:
        assert parse_project(allowed, "p.yaml", folder).elements[0].print_path.dxf.is_file()


def test_paths_inside_the_folder_and_bounded(folder: Path, monkeypatch) -> None:
    (folder / "sub").mkdir()
    p = parse_project(_print_path("sub/../sine_wall.dxf"), "p.yaml", folder)
    assert p.elements[0].print_path.dxf == (folder / "sine_wall.dxf").resolve()
    assert "is a folder" in _error(_print_path("sub"), folder)
    monkeypatch.setattr("fabflow.schema.MAX_MODEL_BYTES", 100)
    assert "MiB" in _error(_print_path("sine_wall.dxf"), folder)


def test_an_outside_file_is_never_echoed(folder: Path) -> None:
    text = (
        "name: x\nlocalization:\n  total_station:\n    observations: /etc/passwd\n"
        "    robot_points: /etc/passwd\nelements: [{cabin: {}}]\n"
    )
    message = _error(text, folder)
    assert "line 4: localization.total_station.observations" in message
    assert "root:" not in message


def test_json_schema_has_limits_and_bounds() -> None:
    schema = project_json_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    assert "limits" in schema["properties"] and "allow_outside_paths" in schema["properties"]
    validator = jsonschema.Draft202012Validator(schema)
    assert list(validator.iter_errors({"name": "x", "elements": [{"cabin": {"length": -1}}]}))


@pytest.mark.parametrize(
    ("robot", "fmt"),
    [("kuka_kr60_3", "krl"), ("abb_irb4600_60_205", "rapid"), ("ur10e", "urscript"),
     ("brokk_170", "json")],
)  # fmt: skip
def test_default_format_is_the_robots_own(robot: str, fmt: str) -> None:
    p = parse_project(f"name: x\nrobot: {{model: {robot}}}\nelements: [{{cabin: {{}}}}]\n")
    assert p.program.format == fmt
