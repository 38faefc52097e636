"""``robot.model: custom``: bad robot definitions are refused with the field named."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml
from custom_robots import TRACK_URDF, kr60, project_text

from fabflow.errors import InputError
from fabflow.project import load_project, project_json_schema


def _without(spec: dict[str, Any], key: str) -> dict[str, Any]:
    out = copy.deepcopy(spec)
    out.pop(key)
    return out


def _robot(**robot: Any) -> dict[str, Any]:
    return robot


_URDF = "<robot name='r'><link name='a'/><link name='b'/></robot>"
_CHAIN = "".join(
    f"<link name='l{i}'/><joint name='j{i}' type='revolute'><parent link='l{i - 1}'/>"
    f"<child link='l{i}'/><limit lower='-1' upper='1' velocity='1'/></joint>"
    for i in range(1, 14)
)

# (robot section, URDF file text or None, field path in the message, words in it)
CASES = [
    ({"custom": _without(kr60(), "joint_limits_deg")}, None,
     "robot.custom.joint_limits_deg", "required field is missing"),
    ({"custom": kr60(joint_speeds_deg_s=[100] * 5)}, None,
     "robot.custom.joint_speeds_deg_s", "6 values"),
    ({"custom": kr60("dh", dh={**kr60("dh")["dh"], "alpha_deg": [-90, 0, -90, 90, -90]})}, None,
     "robot.custom.dh.alpha_deg", "6 values"),
    ({"custom": kr60(opw={**kr60()["opw"], "offsets_deg": [0, -90, 0, 0, 0]})}, None,
     "robot.custom.opw.offsets_deg", "at least 6 items"),
    ({"custom": kr60(opw={**kr60()["opw"], "c2": float("nan")})}, None,
     "robot.custom.opw.c2", "finite"),
    ({"custom": kr60(home_deg=[0, -90, 90, 0, float("inf"), 0])}, None,
     "robot.custom.home_deg[4]", "finite"),
    ({"custom": kr60(vendor="fanuc")}, None, "robot.custom.vendor", "'kuka'"),
    ({"custom": kr60(opw={**kr60()["opw"], "signs": [1, 1, 2, 1, 1, 1]})}, None,
     "robot.custom.opw.signs[2]", "-1"),
    ({"custom": kr60(joint_limits_deg=[[-185, 185], [35, -135]] + [[-350, 350]] * 4)}, None,
     "robot.custom.joint_limits_deg[1]", "lower < upper"),
    ({"custom": kr60(home_deg=[0, -150, 90, 0, 0, 0])}, None,
     "robot.custom.home_deg", "outside the joint limits"),
    ({"custom": kr60(dh=kr60("dh")["dh"])}, None, "robot.custom", "exactly one of"),
    ({"custom": kr60(base_link="a")}, None, "robot.custom.base_link", "only with 'urdf'"),
    ({"custom": kr60(capsules=[{"frame_a": 0, "frame_b": 8, "radius": 0.1}])}, None,
     "robot.custom.capsules[0].frame_b", "frame 8"),
    ({"custom": kr60(name="my arm")}, None, "robot.custom.name", "pattern"),
    ({"model": "custom"}, None, "robot.model", "model: custom"),
    ({"model": "kuka_kr60_3", "custom": kr60()}, None, "robot.custom", "model: custom"),
    ({"custom": kr60(payload=5.0)}, None, "robot.tool.mass", "payload of 5"),
    ({"custom": kr60(vendor="abb"), "__program": {"format": "krl"}}, None,
     "program.format", "ABB"),
    ({"custom": "URDF"}, None, "robot.custom.urdf", "does not exist"),
    ({"custom": "URDF"}, "<robot name='r'><link", "robot.custom.urdf", "not well-formed XML"),
    ({"custom": "URDF"}, _URDF, "robot.custom.tip_link", "no chain of joints"),
    ({"custom": "URDF", "tip": "l13", "base": "l0"}, "<robot name='r'>"
     "<link name='l0'/>" + _CHAIN + "</robot>", "robot.custom.urdf", "more than 12 joints"),
    ({"custom": "URDF", "tip": "tcp", "base": "floor"},
     TRACK_URDF.replace('upper="6"', 'upper="inf"'), "robot.custom.urdf", "limits must be finite"),
]  # fmt: skip


def _write(folder: Path, robot: dict[str, Any], urdf: str | None) -> Path:
    robot = dict(robot)
    program = robot.pop("__program", None)
    base, tip = robot.pop("base", "a"), robot.pop("tip", "b")
    if robot.get("custom") == "URDF":
        robot["custom"] = {
            "name": "u",
            "vendor": "ur",
            "urdf": "arm.urdf",
            "base_link": base,
            "tip_link": tip,
            "home_deg": [0.0] * 5,
            "payload": 10.0,
        }
        if urdf is not None:
            (folder / "arm.urdf").write_text(urdf, encoding="utf-8")
    custom = robot.pop("custom", None)
    doc = yaml.safe_load(project_text(custom, **robot))
    if custom is None:
        doc["robot"] = robot
    if program is not None:
        doc["program"] = program
    path = folder / "project.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


@pytest.mark.parametrize(("robot", "urdf", "where", "what"), CASES)
def test_bad_robot_definitions(tmp_path: Path, robot, urdf, where: str, what: str) -> None:
    path = _write(tmp_path, robot, urdf)
    with pytest.raises(InputError) as info:
        load_project(path)
    message = str(info.value)
    assert "project.yaml" in message
    assert f": {where}: " in message and what in message, message
    assert "Traceback" not in message


# one of each kind the issue names, through the command line: exit code 2, no traceback
CLI_CASES = [0, 1, 4, 6, 18, 19, 20, 21]


@pytest.mark.parametrize("case", CLI_CASES)
def test_fabflow_validate_refuses_bad_definitions(cli, tmp_path: Path, case: int) -> None:
    robot, urdf, where, what = CASES[case]
    result = cli("validate", str(_write(tmp_path, robot, urdf)))
    output = result.stdout + result.stderr
    assert result.returncode == 2, output
    assert where in output and what in output and "Traceback" not in output, output


def test_good_definitions_validate(cli, tmp_path: Path) -> None:
    path = _write(tmp_path, {"custom": kr60("dh")}, None)
    result = cli("validate", str(path))
    assert result.returncode == 0, result.stdout + result.stderr
    project = load_project(path)
    assert project.robot.model == "custom" and project.robot.name.startswith("custom:kr60_")
    assert project.program.format == "krl"


def test_schema_describes_robot_definitions() -> None:
    schema = project_json_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    robot = schema["$defs"]["Robot"]["properties"]
    assert "custom" in robot["model"]["enum"] and "custom" in robot
    assert {"opw", "dh", "urdf", "base_link", "tip_link", "capsules"} <= set(
        schema["$defs"]["CustomRobot"]["properties"]
    )
    doc = yaml.safe_load(project_text(kr60()))
    jsonschema.validate(doc, schema)
