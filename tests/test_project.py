"""The project file: loading, validation messages, JSON schema."""

from __future__ import annotations

import json
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
    ("uwb_without_anchors.yaml", "localization", "anchor positions"),
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
