"""``fabflow plan`` and the ``plan`` build stage."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from helpers import PROJECTS

from fabflow.build.context import BuildContext
from fabflow.build.plan import stage_plan
from fabflow.build.runner import stages
from fabflow.design.generate import generate_elements
from fabflow.output import MARKER
from fabflow.project import load_project
from fabflow.tasks import Plan

FAR_PROJECT = """
name: far
site: {extent_min: [-3, -3], extent_max: [5, 5]}
elements:
  - task_points:
      - {id: near, pose: {xyz: [1.0, 0.0, 1.0], abc_deg: [0, 180, 0]}}
      - {id: far_away, pose: {xyz: [40.0, 0.0, 1.0], abc_deg: [0, 180, 0]}}
"""
NEAR_PROJECT = FAR_PROJECT.replace("[40.0, 0.0, 1.0]", "[2.0, 1.0, 0.8]")


def test_plan_command_writes_plan_json_and_summary(cli, tmp_path: Path):
    out = tmp_path / "out"
    res = cli("plan", str(PROJECTS / "cabin"), "-o", str(out))
    assert res.returncode == 0, res.stderr
    for word in ("stations", "elements per station", "visits", "travel"):
        assert word in res.stdout
    data = json.loads((out / "plan.json").read_text())
    assert data["work_packages"]
    for wp in data["work_packages"]:
        assert wp["station"]["id"].startswith("S")
        assert np.asarray(wp["station"]["T_world_platform"]).shape == (4, 4)
        assert len(wp["elements"]) == len(wp["T_world_targets"]) > 0
    assert (out / "site_plan.dxf").is_file()
    plan = Plan.from_dict(data)
    assert plan.summary["stations"] == len(plan.stations)


def test_infeasible_project_fails_cleanly_and_writes_nothing(cli, tmp_path: Path):
    project = tmp_path / "far.yaml"
    project.write_text(FAR_PROJECT)
    out = tmp_path / "out"
    out.mkdir()
    (out / MARKER).write_text("")  # an earlier fabflow output
    (out / "previous.txt").write_text("kept")
    res = cli("plan", str(project), "-o", str(out))
    assert res.returncode == 2
    assert "far_away" in res.stderr and "near" not in res.stderr.replace("far_away", "")
    assert "Traceback" not in res.stderr
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "previous.txt"]
    assert not list(tmp_path.glob(".out.staging-*"))


def test_plan_stage_sets_result_and_summary_rows(tmp_path: Path):
    assert [name for name, _ in stages()].index("plan") > [n for n, _ in stages()].index("design")
    (tmp_path / "near.yaml").write_text(NEAR_PROJECT)
    project = load_project(tmp_path / "near.yaml")
    tmp_path = tmp_path / "out"
    tmp_path.mkdir()
    ctx = BuildContext(project=project, out=tmp_path)
    ctx.elements = generate_elements(project.elements, project.path)
    stage_plan(ctx)
    ctx.finish()
    plan = ctx.plan
    assert isinstance(plan, Plan)
    assert sorted(e for wp in plan.work_packages for e in wp.elements) == ["far_away", "near"]
    items = {item for stage, item, _ in ctx.summary if stage == "plan"}
    assert {"stations", "elements per station", "visits", "travel"} <= items
    assert (tmp_path / "plan.json").is_file() and (tmp_path / "site_plan.dxf").is_file()
