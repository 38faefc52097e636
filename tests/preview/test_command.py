"""``fabflow preview``: export and live mode on a small project, inputs, errors, build stage."""

from __future__ import annotations

import dataclasses
import io
import json
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pytest
from helpers import PROJECTS
from typer.testing import CliRunner

from fabflow.build.context import BuildContext
from fabflow.build.preview import stage_preview
from fabflow.cli import app
from fabflow.design.generate import generate_elements
from fabflow.errors import InputError
from fabflow.positioning.result import BasePose
from fabflow.preview.command import project_program_source, run_preview
from fabflow.preview.inputs import model_for_project, read_base_poses, read_deviations
from fabflow.project import load_project
from fabflow.tasks.planner import plan_project

TINY = """\
name: tiny
site:
  extent_min: [-3.0, -3.0]
  extent_max: [5.0, 5.0]
robot:
  model: kuka_kr60_3
localization:
  method: total_station
elements:
  - cabin:
      length: 1.8
      width: 1.2
      height: 0.42
      eave_height: 0.42
      openings: []
"""


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("tiny")
    (folder / "project.yaml").write_text(TINY, encoding="utf-8")
    return folder


@pytest.fixture(scope="module")
def planned(tiny: Path):
    project = load_project(tiny)
    elements = generate_elements(project.elements, project.path)
    return project, elements, plan_project(project, elements)


def test_export_command_writes_one_html_file(tiny: Path, tmp_path: Path) -> None:
    out = tmp_path / "tiny.html"
    result = CliRunner().invoke(app, ["preview", str(tiny), "--export", str(out)])
    assert result.exit_code == 0, result.output
    assert "wrote" in result.output and "steps" in result.output
    html = out.read_text(encoding="utf-8")
    assert html.startswith("<!") and "__VISER_EMBED_DATA__" in html


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--colour-by", "rainbow"], "--colour-by must be one of"),
        (["--colour-by", "deviation"], "--sim DIR"),
        (["--export", "/nonexistent-folder/x.html"], "does not exist"),
        (["--sim", "/nonexistent-folder", "--export", "x.html"], "does not exist"),
    ],
)
def test_bad_options_are_one_message_and_exit_2(tiny: Path, args: list[str], message: str) -> None:
    result = CliRunner().invoke(app, ["preview", str(tiny), *args])
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert "Traceback" not in result.output


def test_live_mode_serves_the_page(tiny: Path) -> None:
    seen: list[str] = []
    pages: list[bytes] = []

    def wait() -> None:
        url = seen[-1].split(" at ")[1].split()[0]
        with urllib.request.urlopen(url, timeout=30) as response:
            pages.append(response.read())

    run_preview(tiny, port=0, say=seen.append, wait=wait)
    assert "preview of 'tiny' at http://127.0.0.1:" in seen[-1]
    assert b"<html" in pages[0].lower()


def test_sim_folder_gives_deviation_colours_and_base_poses(planned, tmp_path: Path) -> None:
    project, elements, plan = planned
    blocks = [e for e in elements if e.robot_built][:4]
    rows = ["run,element_id,deviation_m"]
    for run in range(2):
        rows += [f"{run},{e.id},{0.001 * (i + 1) * (run + 1)}" for i, e in enumerate(blocks)]
    (tmp_path / "elements.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    (tmp_path / "summary.json").write_text(json.dumps({"rmse": 0.01}), encoding="utf-8")
    wp = plan.work_packages[0]
    pose = BasePose(
        T_world_base=np.eye(4),
        covariance=np.eye(6) * 1e-6,
        method="total_station",
        residuals=np.full((4, 3), 0.001),
        rmse=0.0017,
        station=wp.station.id,
    )
    (tmp_path / "stations").mkdir()
    pose.write(tmp_path / "stations" / "base_pose.json")
    (tmp_path / "localization").mkdir()
    second = plan.work_packages[1].station.id
    visit_pose = BasePose(
        T_world_base=np.eye(4), covariance=np.eye(6), method="uwb", station=second
    )
    visit_pose.write(tmp_path / "localization" / f"visit_02_{second}.json")

    dev = read_deviations(tmp_path)
    assert dev[blocks[1].id] == pytest.approx((0.002 + 0.004) / 2)
    poses = read_base_poses(tmp_path)
    assert poses[wp.station.id].rmse == pytest.approx(0.0017)
    assert poses[1].method == "uwb" and set(poses) == {wp.station.id, 1}

    model = model_for_project(project, elements, plan, sim_dir=tmp_path)
    assert "deviation" in model.colour_modes()
    colours = model.element_colours("deviation", 0)
    i0, i3 = (model.elements.index(b) for b in (blocks[0], blocks[3]))
    assert colours[i0, 0] < colours[i3, 0]  # redder with more deviation
    assert model.localization_at(0).rmse == pytest.approx(0.0017)

    out = tmp_path / "dev.html"
    result = CliRunner().invoke(
        app,
        ["preview", str(project.path), "--sim", str(tmp_path), "--colour-by", "deviation",
         "--export", str(out)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert out.stat().st_size > 0


def test_bad_deviation_table_names_file_and_line(tmp_path: Path) -> None:
    (tmp_path / "d.csv").write_text("element,deviation_m\nB0000,0.001\nB0001,abc\n")
    with pytest.raises(InputError, match=r"d\.csv: line 3: column 'deviation_m'"):
        read_deviations(tmp_path)
    (tmp_path / "d.csv").write_text("a,b\n1,2\n")
    with pytest.raises(InputError, match="no per-element deviation table"):
        read_deviations(tmp_path)


def test_download_gives_the_projects_program(planned) -> None:
    project, elements, plan = planned
    model = model_for_project(project, elements, plan)
    name, data = project_program_source(project, elements, plan, model)(0)
    assert name.endswith(".zip")
    names = zipfile.ZipFile(io.BytesIO(data)).namelist()
    assert {Path(n).suffix for n in names} == {".src", ".dat"}


def test_build_stage_writes_preview_html(planned, tmp_path: Path) -> None:
    project, elements, plan = planned
    ctx = BuildContext(project=project, out=tmp_path)
    ctx.elements, ctx.plan = elements, plan
    stage_preview(ctx)
    assert (tmp_path / "preview.html").stat().st_size == ctx.preview.size_bytes
    assert any(stage == "preview" for stage, _, _ in ctx.summary)


def test_build_folder_gives_localization_results(tiny: Path, planned, tmp_path: Path) -> None:
    project, elements, plan = planned
    loc = tmp_path / "localization"
    loc.mkdir()
    for wp in plan.work_packages:
        BasePose(
            T_world_base=np.eye(4),
            covariance=np.eye(6) * 4e-6,
            method="total_station",
            residuals=np.full((3, 3), 0.002),
            rmse=0.0035,
            station=wp.station.id,
        ).write(loc / f"visit_{wp.index + 1:02d}_{wp.station.id}.json")
    model = model_for_project(project, elements, plan, sim_dir=tmp_path)
    assert model.deviation is None
    assert all(model.localization_at(p).rmse == 0.0035 for p in range(len(plan.work_packages)))
    result = CliRunner().invoke(
        app,
        ["preview", str(tiny), "--sim", str(tmp_path), "--colour-by", "deviation",
         "--export", str(tmp_path / "x.html")],
    )  # fmt: skip
    assert result.exit_code == 2 and "localization results only" in result.output
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="holds neither"):
        model_for_project(project, elements, plan, sim_dir=empty)


def test_build_folder_plan_is_used_and_foreign_results_are_rejected(
    tiny: Path, planned, tmp_path: Path
) -> None:
    from fabflow.design.elements import elements_to_json
    from fabflow.output import write_json
    from fabflow.preview.inputs import read_build_outputs
    from fabflow.tasks.plan import Plan

    project, elements, plan = planned
    # a build whose plan visits the stations in reverse order
    packages = tuple(
        dataclasses.replace(wp, index=i) for i, wp in enumerate(reversed(plan.work_packages))
    )
    reversed_plan = Plan(work_packages=packages)
    write_json(tmp_path / "plan.json", {"fabflow_version": "x", **reversed_plan.to_dict()})
    write_json(tmp_path / "elements.json", {"elements": elements_to_json(elements)})
    (tmp_path / "localization").mkdir()
    last = packages[-1]
    BasePose(
        T_world_base=np.eye(4), covariance=np.eye(6), method="uwb", station=last.station.id
    ).write(tmp_path / "localization" / f"visit_{len(packages):02d}_{last.station.id}.json")

    read_elements, read_plan = read_build_outputs(tmp_path)
    assert [e.id for e in read_elements] == [e.id for e in elements]
    assert [wp.elements for wp in read_plan.work_packages] == [wp.elements for wp in packages]
    model = model_for_project(project, sim_dir=tmp_path)
    assert model.element_at(1).id == packages[0].elements[0]
    assert model.localization_at(len(packages) - 1).method == "uwb"
    if len(packages) > 1 and packages[0].station.id != last.station.id:
        with pytest.raises(InputError, match="made for another plan"):
            model_for_project(project, elements, plan, sim_dir=tmp_path)
    (tmp_path / "plan.json").write_text("{not json")
    with pytest.raises(InputError, match=r"plan\.json: cannot read build output"):
        read_build_outputs(tmp_path)


@pytest.mark.parametrize("project", sorted(p.name for p in PROJECTS.iterdir() if p.is_dir()))
def test_every_example_project_exports_its_preview(project: str, tmp_path: Path) -> None:
    out = tmp_path / f"{project}.html"
    result = CliRunner().invoke(app, ["preview", str(PROJECTS / project), "--export", str(out)])
    assert result.exit_code == 0, result.output
    html = out.read_text(encoding="utf-8")
    assert html.startswith("<!") and "__VISER_EMBED_DATA__" in html


@pytest.fixture(scope="module")
def split_paths():
    """The print path project: its wide layers are split into per-station pieces."""
    project = load_project(PROJECTS / "print_path")
    elements = generate_elements(project.elements, project.path)
    plan = plan_project(project, elements)
    assert plan.split_elements, "the example no longer splits its print paths"
    return project, elements, plan


def test_a_plan_with_split_print_paths_previews_from_the_design(split_paths, tmp_path) -> None:
    project, elements, plan = split_paths
    model = model_for_project(project, elements, plan)
    ids = {e.id for e in model.elements}
    assert {p.id for p in plan.split_elements} <= ids
    assert not {str(p.attributes["parent"]) for p in plan.split_elements} & ids
    assert model.n_steps == sum(len(wp.elements) for wp in plan.work_packages)
    package = next(
        k for k, wp in enumerate(plan.work_packages) if "." in wp.elements[0]
    )  # a package that prints pieces
    name, data = project_program_source(project, elements, plan, model)(package)
    assert data and name


def test_a_build_folder_with_split_print_paths_previews(split_paths, tmp_path) -> None:
    project, elements, plan = split_paths
    (tmp_path / "elements.json").write_text(
        json.dumps({"elements": [e.to_dict() for e in elements]}), encoding="utf-8"
    )
    (tmp_path / "plan.json").write_text(json.dumps(plan.to_dict()), encoding="utf-8")
    (tmp_path / "localization").mkdir()
    wp = plan.work_packages[0]
    BasePose(
        T_world_base=np.eye(4), covariance=np.eye(6) * 1e-6, method="uwb",
        station=wp.station.id,
    ).write(tmp_path / "localization" / f"visit_01_{wp.station.id}.json")  # fmt: skip
    out = tmp_path / "preview.html"
    result = CliRunner().invoke(
        app, ["preview", str(project.path), "--sim", str(tmp_path), "--export", str(out)]
    )
    assert result.exit_code == 0, result.output
    assert out.stat().st_size > 0


def test_live_preview_of_split_print_paths(split_paths) -> None:
    project = split_paths[0]
    seen: list[str] = []
    run_preview(project.path, port=0, say=seen.append, wait=lambda: None)
    assert "preview of 'print_path' at http://127.0.0.1:" in seen[-1]
