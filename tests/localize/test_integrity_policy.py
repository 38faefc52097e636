"""The build refuses a failed visit, or warns and writes no program for it."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from helpers import DATA, PROJECTS

from fabflow.errors import LocalizationError
from fabflow.localize.plan import check_visit, check_visits, localize_plan
from fabflow.positioning.integrity import Integrity, exact
from fabflow.positioning.result import BasePose
from fabflow.project import load_project, parse_project
from fabflow.transforms.se3 import make_T

SMALL = DATA / "sim" / "project.yaml"


def _far_anchors(text: str) -> str:
    # the anchors surveyed 20 m away from where the stations are: every visit lies
    # outside their coverage
    return text.replace(
        "T_world_uwb: {xyz: [-1.0, -1.0, 0.0]}", "T_world_uwb: {xyz: [20.0, 20.0, 0.0]}"
    )


def _parked_off(text: str, on_failure: str) -> str:
    # the platform parks 30 cm off its station while the project trusts it to 1 mm:
    # the pose, however well measured, fails the check against the planned station
    return text.replace(
        "localization:\n",
        f"localization:\n  integrity: {{on_failure: {on_failure}, parking_sigma: 0.001}}\n",
        1,
    ).replace("simulation:\n", "simulation:\n  driving_error: 0.3\n", 1)


def test_anchors_that_cover_no_station_are_a_planning_error(tmp_path: Path, cli) -> None:
    bad = tmp_path / "project.yaml"
    bad.write_text(_far_anchors(SMALL.read_text()))
    res = cli("build", str(bad), "-o", str(tmp_path / "out"))
    assert res.returncode == 2, res.stdout + res.stderr
    assert "UWB anchors do not cover station S1" in res.stderr
    assert "localization.uwb.anchors" in res.stderr
    assert not (tmp_path / "out").exists()


def test_refuse_stops_the_build_naming_visit_and_reason(tmp_path: Path, cli) -> None:
    bad = tmp_path / "project.yaml"
    bad.write_text(_parked_off(SMALL.read_text(), "refuse"))
    res = cli("build", str(bad), "-o", str(tmp_path / "out"))
    assert res.returncode == 2, res.stdout + res.stderr
    assert "visit 1 at station S1 (uwb): integrity failed" in res.stderr
    assert "from the planned station" in res.stderr
    assert not (tmp_path / "out").exists()


def test_warn_builds_without_programs_for_failed_visits(tmp_path: Path, cli) -> None:
    bad = tmp_path / "project.yaml"
    bad.write_text(_parked_off(SMALL.read_text(), "warn"))
    res = cli("build", str(bad), "-o", str(tmp_path / "out"))
    assert res.returncode == 0, res.stderr
    assert "no program (localization failed)" in res.stdout
    assert not list((tmp_path / "out" / "programs").iterdir())
    visit = json.loads(next((tmp_path / "out" / "localization").glob("visit_*.json")).read_text())
    assert visit["integrity"]["status"] == "failed"


def test_every_visit_of_the_cabin_passes_and_is_recorded(tmp_path: Path) -> None:
    project = load_project(PROJECTS / "cabin")
    from fabflow.design.generate import generate_elements
    from fabflow.tasks.planner import make_plan

    elements = generate_elements(project.elements, project.path)
    plan = make_plan(project, elements)
    results = localize_plan(project, plan, elements, np.random.default_rng(0))
    for estimate, _ in results.values():
        assert estimate.integrity is not None and estimate.integrity.status == "ok"
        assert estimate.integrity.checks["planned_station"]["passed"]
        assert estimate.integrity.protection_level["horizontal"] > 0


def test_planned_station_check_catches_a_shifted_pose() -> None:
    project = parse_project(SMALL.read_text())
    T = make_T(np.eye(3), [1.0, 1.0, 0.6])
    cov = np.diag([1e-6, 1e-6, 1e-6, 1.0, 1.0, 1e-6])
    ok = Integrity(status="ok")
    good = check_visit(project, BasePose(T, cov, "uwb", integrity=ok), T)
    assert good.integrity is not None and good.integrity.status == "ok"
    shifted = T.copy()
    shifted[0, 3] += 0.3  # 30 cm off with a 2 cm parking accuracy
    bad = check_visit(project, BasePose(shifted, cov, "uwb", integrity=ok), T)
    assert bad.integrity is not None and bad.integrity.failed
    assert "from the planned station" in bad.integrity.reason
    mirrored = T.copy()
    mirrored[2, 3] -= 0.9  # the mirror image below near-coplanar anchors
    low = check_visit(project, BasePose(mirrored, cov, "uwb", integrity=ok), T)
    assert low.integrity is not None and low.integrity.failed
    nan = check_visit(project, BasePose(np.full((4, 4), np.nan), cov, "uwb", integrity=ok), T)
    assert nan.integrity is not None and "not finite" in nan.integrity.reason
    untested = check_visit(project, BasePose(T, cov, "uwb"), T)
    assert untested.integrity is not None and untested.integrity.failed
    # all of them checked at once (a simulated run's visits), with an exact one and a
    # planned pose of their own each: what each gets alone
    poses = [good, bad, low, nan, untested]
    estimates = [replace(p, integrity=None if p is untested else ok) for p in poses]
    estimates.append(BasePose(shifted, cov, "uwb", integrity=exact("noise-free")))
    planned = np.stack([T, T, T, T, T, T])
    planned[0, 1, 3] += 0.01
    together = check_visits(project, estimates, planned)
    for estimate, T_planned, got in zip(estimates, planned, together, strict=True):
        want = check_visit(project, estimate, T_planned)
        assert got.integrity == want.integrity
    assert together[1].integrity.failed and together[-1].integrity.status == "ok"


def test_no_program_from_a_failed_pose() -> None:
    from fabflow.design.generate import generate_elements
    from fabflow.programs.compile import write_programs
    from fabflow.tasks.planner import make_plan

    project = load_project(SMALL)
    elements = generate_elements(project.elements, project.path)
    plan = make_plan(project, elements)
    results = localize_plan(project, plan, elements, np.random.default_rng(0))
    poses = {i: est for i, (est, _) in results.items()}
    first = min(poses)
    failed = poses[first].integrity.failing("test")  # type: ignore[union-attr]
    poses[first] = BasePose(
        poses[first].T_world_base, poses[first].covariance, "uwb", integrity=failed
    )
    with pytest.raises(LocalizationError, match="failed its integrity tests"):
        write_programs(plan, elements, project, poses)
