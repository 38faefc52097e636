"""The command line end to end: exit codes, messages, atomic outputs."""

from __future__ import annotations

import importlib.metadata
import json
import math
from pathlib import Path

import ezdxf
import pytest
from helpers import PROJECTS, ROOT

from fabflow.build import runner
from fabflow.build.runner import run_build
from fabflow.errors import InfeasibleError
from fabflow.output import MARKER, atomic_output_dir
from fabflow.project import load_project
from fabflow.version import __version__

BAD = ROOT / "tests" / "data" / "bad_projects"


def test_validate_ok(cli) -> None:
    result = cli("validate", "projects/cabin/project.yaml")
    assert result.returncode == 0, result.stderr
    assert "is valid" in result.stdout


@pytest.mark.parametrize(
    ("name", "where"),
    [
        ("wrong_type.yaml", "elements[0].cabin.block.length"),
        ("missing_field.yaml", "name: required field is missing"),
        ("unknown_key.yaml", "robot.colour"),
        ("missing_path.yaml", "elements[0].print_path.dxf"),
        ("bad_yaml.yaml", "line 4, column 1"),
    ],
)
@pytest.mark.parametrize("command", ["validate", "build"])
def test_bad_input_exits_2_without_traceback(cli, tmp_path, name, where, command) -> None:
    args = [command, str(BAD / name)]
    if command == "build":
        args += ["-o", str(tmp_path / "out")]
    result = cli(*args)
    assert result.returncode == 2
    assert where in result.stderr
    assert name in result.stderr
    assert "Traceback" not in result.stdout + result.stderr
    assert not (tmp_path / "out").exists()


def test_missing_project_file(cli, tmp_path) -> None:
    result = cli("validate", str(tmp_path / "nothing.yaml"))
    assert result.returncode == 2
    assert "does not exist" in result.stderr


def test_schema_prints_json(cli) -> None:
    result = cli("schema")
    assert result.returncode == 0
    schema = json.loads(result.stdout)
    assert schema["title"] == "fabflow project"
    assert "elements" in schema["required"]


def test_version(cli) -> None:
    result = cli("--version")
    assert result.returncode == 0
    assert result.stdout.strip() == f"fabflow {__version__}"


def test_version_is_the_installed_distribution_version() -> None:
    # the literal in fabflow/version.py is what the package metadata reads; an
    # install made before the literal changed shows up here
    assert __version__ == importlib.metadata.version("fabflow")


@pytest.mark.parametrize("name", ["cabin", "print_path", "excavator_print", "timber_wall"])
def test_build_example_projects(cli, tmp_path, name) -> None:
    out = tmp_path / name
    result = cli("build", str(PROJECTS / name), "-o", str(out))
    assert result.returncode == 0, result.stderr
    project = json.loads((out / "project.json").read_text())
    assert project["project"]["name"] == name
    summary = json.loads((out / "summary.json").read_text())
    assert {"stage": "project", "item": "name", "value": name} in summary
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_the_village_plans_where_its_localization_stands(cli, tmp_path) -> None:
    out = tmp_path / "village"
    result = cli("plan", str(PROJECTS / "village"), "-o", str(out))
    assert result.returncode == 0, result.stderr
    plan = json.loads((out / "plan.json").read_text())
    layout = json.loads((out / "instrument_setups.json").read_text())
    covered = [k for s in layout["setups"] for k in range(s["packages"][0], s["packages"][1] + 1)]
    assert covered == list(range(1, len(plan["work_packages"]) + 1))
    assert len(layout["setups"]) > 1  # the instrument moves as the village grows
    assert "set-up T2" in result.stdout
    for setup in layout["setups"]:  # each sights its control points within max_range
        eye = setup["position"]
        assert len(setup["control_points"]) >= 3
        for c in setup["control_points"]:
            assert math.dist(layout["control_points"][c], eye) <= 14.0
    doc = ezdxf.readfile(out / "site_plan.dxf")
    texts = {e.dxf.text.split()[0] for e in doc.modelspace().query("TEXT")}
    assert {s["id"] for s in layout["setups"]} <= texts
    assert set(layout["control_points"]) <= texts


def test_atomic_output_keeps_previous_result_on_failure(tmp_path, monkeypatch) -> None:
    project = load_project(PROJECTS / "cabin")
    out = tmp_path / "out"
    run_build(project, out)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    (out / "marker.txt").write_text("from the previous run")

    written: list[Path] = []

    def failing_stage(ctx: runner.BuildContext) -> None:
        (ctx.out / "half.json").write_text("{")
        written.append(ctx.out)
        raise InfeasibleError("cannot build this")

    original = runner.stages
    monkeypatch.setattr(runner, "stages", lambda p: [*original(p), ("fail", failing_stage)])
    with pytest.raises(InfeasibleError):
        run_build(project, out)
    assert written and not written[0].exists(), "staging folder must be removed"
    assert (out / "marker.txt").read_text() == "from the previous run"
    assert not (out / "half.json").exists()
    for name, data in before.items():
        assert (out / name).read_bytes() == data
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_atomic_output_replaces_whole_folder(tmp_path) -> None:
    out = tmp_path / "out"
    with atomic_output_dir(out) as staging:
        (staging / "stale.txt").write_text("old")
    with atomic_output_dir(out) as staging:
        (staging / "new.txt").write_text("new")
        assert not (out / "new.txt").exists(), "nothing appears before completion"
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_foreign_folder_is_never_replaced(cli, tmp_path) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    result = cli("plan", str(PROJECTS / "cabin"), "-o", str(out))
    assert result.returncode == 2
    assert "not written by fabflow" in result.stderr
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]


@pytest.mark.parametrize("where", ["/", "file.txt/below"])
def test_unusable_output_paths_exit_2(cli, tmp_path, where) -> None:
    (tmp_path / "file.txt").write_text("x")
    target = where if where == "/" else str(tmp_path / where)
    result = cli("validate", str(PROJECTS / "cabin"))
    assert result.returncode == 0
    result = cli("plan", str(PROJECTS / "cabin"), "-o", target)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert (tmp_path / "file.txt").read_text() == "x"


def test_output_path_that_is_a_file(cli, tmp_path) -> None:
    target = tmp_path / "file.txt"
    target.write_text("keep me")
    result = cli("build", str(PROJECTS / "cabin"), "-o", str(target))
    assert result.returncode == 2
    assert "not a folder" in result.stderr
    assert target.read_text() == "keep me"
