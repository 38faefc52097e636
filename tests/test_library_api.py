"""The five library calls of the README on a project whose print paths are split."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import fabflow
from fabflow.tasks.split import with_pieces

ROOT = Path(__file__).resolve().parents[1]


def test_the_library_takes_the_designed_elements_of_split_print_paths() -> None:
    # the plan names the pieces of split print paths; localize_plan and
    # write_programs once needed the caller to put them in (a KeyError otherwise)
    project = fabflow.load_project(ROOT / "projects" / "print_path")
    elements = fabflow.generate_elements(project.elements, project.path)
    plan = fabflow.make_plan(project, elements)
    assert plan.split_elements
    pieced = with_pieces(elements, plan.split_elements)
    assert with_pieces(pieced, plan.split_elements) == pieced

    poses = fabflow.localize_plan(project, plan, elements, np.random.default_rng(0))
    again = fabflow.localize_plan(project, plan, pieced, np.random.default_rng(0))
    assert poses.keys() == again.keys()
    for visit, (estimate, T_true) in poses.items():
        np.testing.assert_array_equal(estimate.T_world_base, again[visit][0].T_world_base)
        np.testing.assert_array_equal(T_true, again[visit][1])

    base_poses = {visit: estimate for visit, (estimate, _) in poses.items()}
    programs, files = fabflow.write_programs(plan, elements, project, base_poses, fmt="json")
    _, files_pieced = fabflow.write_programs(plan, pieced, project, base_poses, fmt="json")
    assert files == files_pieced
    assert len(programs) == sum(1 for wp in plan.work_packages if wp.elements)
