"""The collision check misses nothing an independent replay finds, on the examples.

The JSON command stream of each example's first work package is replayed
through the independent kinematics and geometry of ``tests/collision_replay.py``
(its own OPW forward kinematics, sampled capsules, numpy point-box distances)
against the structure as built. Every move the replay finds cutting into an
obstacle must be one the planner's check (:mod:`fabflow.programs.collision`)
reports too. The examples still collide (their projects set
``program.check_collisions: false``); ``benchmarks/collisions.py`` counts the
contacts of every program.
"""

from __future__ import annotations

import numpy as np
import pytest
from collision_replay import replay
from helpers import PROJECTS

from fabflow.design.generate import generate_elements
from fabflow.localize.plan import localize_plan
from fabflow.programs.collision import Contact, check_package
from fabflow.programs.collision_model import environment
from fabflow.programs.compile import work_package_program
from fabflow.programs.writers.json_stream import write_json_stream
from fabflow.project import load_project
from fabflow.tasks.planner import make_plan
from fabflow.tasks.split import with_pieces


def _first_package(name: str) -> tuple[list, list[Contact]]:
    """The replay's contacts and the planner's check's contacts of the first package."""
    project = load_project(PROJECTS / name)
    project = project.model_copy(
        update={"simulation": project.simulation.model_copy(update={"sensor_noise": False})}
    )
    elements = generate_elements(project.elements, project.path)
    plan = make_plan(project, elements)
    elements = with_pieces(elements, plan.split_elements)
    by_id = {e.id: e for e in elements}
    located = localize_plan(project, plan, elements, np.random.default_rng(0))
    built = [e for e in elements if not e.robot_built]
    wp = next(w for w in plan.work_packages if w.elements and w.index in located)
    pose = located[wp.index][0]
    program = work_package_program(wp, by_id, project, pose, built)
    stream = next(iter(write_json_stream(program).values()))
    replayed = replay(stream, elements, [e.id for e in built], project.program.clearance, True)
    package = [by_id[e] for e in wp.elements]
    obstacles = environment(project, np.asarray(pose.T_world_base), built, package)
    return replayed, check_package(program, project, obstacles, package)


@pytest.mark.parametrize("name", ["cabin", "print_path"])
def test_the_check_misses_no_penetration_the_replay_finds(name: str) -> None:
    replayed, contacts = _first_package(name)
    checked = {(c.element, c.label) for c in contacts}
    deep = {(element, label) for element, label, _, _, distance in replayed if distance < -0.005}
    assert deep <= checked, sorted(deep - checked)[:5]
    assert all(np.isfinite(c.distance) for c in contacts)
