"""Fixtures of the program tests: the writer test program and the cabin built up to programs."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import PROJECTS
from program_cases import sample_program

from fabflow.build.context import BuildContext
from fabflow.build.runner import run_build
from fabflow.programs.ir import Program
from fabflow.project import Project, load_project


@pytest.fixture(scope="module")
def kuka_program() -> Program:
    """The test program of :mod:`program_cases` for the KUKA KR 60-3."""
    return sample_program()


def _build(project: Project, tmp: Path) -> tuple[Path, BuildContext]:
    out = tmp / "out"
    return out, run_build(project, out, until="program")


@pytest.fixture(scope="session")
def cabin_build(tmp_path_factory) -> tuple[Path, BuildContext]:
    """The cabin as its project says (KUKA KR 60-3, KRL, lift set by the operator)."""
    return _build(load_project(PROJECTS / "cabin"), tmp_path_factory.mktemp("cabin"))


@pytest.fixture(scope="session")
def cabin_abb_build(tmp_path_factory) -> tuple[Path, BuildContext]:
    """The cabin for an ABB IRB 4600 in RAPID, the lift on axis E1, 200 motions a module.

    The IRB 4600 keeps its catalogue HOME (the cabin's is the KR 60-3's); the cabin
    was planned for the KR 60-3, so what the IRB 4600 still collides with is
    reported in the programs rather than failing the build."""
    project = load_project(PROJECTS / "cabin")
    platform = project.robot.platform.model_copy(update={"lift_axis": "E1"})
    robot = project.robot.model_copy(
        update={"model": "abb_irb4600_60_205", "platform": platform, "home_deg": None}
    )
    program = project.program.model_copy(
        update={"format": "rapid", "module_motions": 200, "check_collisions": "report"}
    )
    project = project.model_copy(update={"robot": robot, "program": program})
    return _build(project, tmp_path_factory.mktemp("cabin_abb"))
