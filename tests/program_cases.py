"""The program every writer test compiles: a few elements before a base, per robot.

Golden files live in tests/golden/programs/; regenerate them after an intended
change with ``FABFLOW_UPDATE_GOLDEN=1 pytest tests/programs/writers`` and review
the diff.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from helpers import ROOT

from fabflow.design.elements import Element
from fabflow.programs.assemble import compile_program
from fabflow.programs.compile import element_payloads
from fabflow.programs.ir import Program
from fabflow.programs.motions import work_package_motion
from fabflow.project import load_project
from fabflow.transforms.so3 import exp_so3

GOLDEN = ROOT / "tests" / "golden" / "programs"
PROJECT = ROOT / "tests" / "data" / "programs" / "project.yaml"


def golden(files: dict[str, str], folder: Path) -> dict[str, str]:
    """The golden files in ``folder`` by name; with ``FABFLOW_UPDATE_GOLDEN`` set,
    ``files`` are written there first."""
    if os.environ.get("FABFLOW_UPDATE_GOLDEN"):
        folder.mkdir(parents=True, exist_ok=True)
        for name, text in files.items():
            (folder / name).write_text(text, encoding="utf-8")
    return {p.name: p.read_text(encoding="utf-8") for p in folder.iterdir()}


def make_pose(xyz, yaw=0.0, flip=False) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.array([0.0, 0.0, yaw]))
    if flip:
        T[:3, :3] = T[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = xyz
    return T


def sample_elements() -> list[Element]:
    size = np.array([0.6, 0.105, 0.105])
    return [
        Element(
            "B1", "block", make_pose([3.2, 1.0, 0.0525]), extents=size, attributes={"mass": 2.98}
        ),
        Element("B2", "block", make_pose([3.0, 1.8, 0.1575], yaw=np.pi / 2), extents=size),
        Element(
            "P1",
            "print_path",
            make_pose([3.4, 0.6, 0.3]),
            polyline=np.array([[0.0, 0.0, 0.0], [0.1, 0.05, 0.0], [0.2, 0.0, 0.0]]),
            attributes={"speed": 0.1},
        ),
        Element(
            "T1",
            "task_point",
            make_pose([3.0, 0.5, 0.3], flip=True),
            attributes={"action": "drill"},
        ),
    ]


T_WORLD_BASE = make_pose([2.0, 1.0, 0.6], yaw=0.1)
BASE_OF_ROBOT = {"ur10e": make_pose([2.7, 1.0, 0.5], yaw=0.1)}
"""The UR10e reaches 1.3 m only: its base stands closer to the elements."""


def sample_program(robot: str = "kuka_kr60_3") -> Program:
    project = load_project(PROJECT)
    project = project.model_copy(
        update={"robot": project.robot.model_copy(update={"model": robot})}
    )
    T_world_base = BASE_OF_ROBOT.get(robot, T_WORLD_BASE)
    elements = sample_elements()
    steps = work_package_motion(elements, project, T_world_base)
    header = {"project": project.name, "station": "S1", "generator": "fabflow test"}
    return compile_program(
        "writer test S1",
        steps,
        project,
        T_world_base,
        header,
        lift=0.35,
        payloads=element_payloads(elements),
    )


CASES = [
    ("krl", "kuka_kr60_3"),
    ("rapid", "abb_irb4600_60_205"),
    ("urscript", "ur10e"),
    ("json", "kuka_kr60_3"),
]
