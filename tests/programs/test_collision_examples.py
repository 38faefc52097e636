"""The examples' programs against an independent replay of their command streams.

The JSON command streams of each example's first work packages (one per
station for the print wall) are replayed through the independent kinematics and
geometry of ``tests/collision_replay.py`` (its own OPW forward kinematics,
sampled capsules, numpy point-box distances, its own rules for the seat moves
and for the hand-built elements) against the structure as built. Every move the
replay finds cutting into an obstacle must be one the planner's check
(:mod:`fabflow.programs.collision`) reports too, and these programs, re-planned
by the check, replay without a contact at the clearance. ``benchmarks/collisions.py``
replays every program of both examples.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from collision_replay import replay
from helpers import PROJECTS

from fabflow.design.elements import structure_timeline
from fabflow.design.generate import generate_elements
from fabflow.localize.plan import localize_plan
from fabflow.programs.collision import SEAT_TOLERANCE, Contact, check_package
from fabflow.programs.collision_model import environment
from fabflow.programs.compile import work_package_program
from fabflow.programs.writers.json_stream import write_json_stream
from fabflow.project import load_project
from fabflow.tasks.planner import make_plan
from fabflow.tasks.split import with_pieces

PACKAGES = {"cabin": 1, "print_path": 2}
"""How many of each example's first work packages are replayed (the print wall's
first two are one per station)."""


@cache
def _replayed(name: str, plain: bool = False) -> list[tuple[str, list, list[Contact]]]:
    """Per replayed package: its program name, the replay's and the check's contacts.

    ``plain``: the programs without the collision re-planning (``check_collisions``
    off), which still collide, so that the two are compared on contacts."""
    project = load_project(PROJECTS / name)
    program = project.program.model_copy(update={"check_collisions": False})
    project = project.model_copy(
        update={
            "simulation": project.simulation.model_copy(update={"sensor_noise": False}),
            **({"program": program} if plain else {}),
        }
    )
    elements = generate_elements(project.elements, project.path)
    plan = make_plan(project, elements)
    elements = with_pieces(elements, plan.split_elements)
    by_id = {e.id: e for e in elements}
    located = localize_plan(project, plan, elements, np.random.default_rng(0))
    timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
    packages = [
        (wp, built, coming)
        for wp, (built, coming) in zip(plan.work_packages, timeline, strict=True)
        if wp.elements and wp.index in located
    ]
    out = []
    for wp, built, coming in packages[: PACKAGES[name]]:
        pose = located[wp.index][0]
        program = work_package_program(wp, by_id, project, pose, built, coming)
        stream = next(iter(write_json_stream(program).values()))
        robot = [e.id for e in built if e.robot_built]  # the replay adds the hand-built ones
        replayed = replay(stream, elements, robot, project.program.clearance)
        package = [by_id[e] for e in wp.elements]
        obstacles = environment(project, np.asarray(pose.T_world_base), built, package, coming)
        out.append((program.name, replayed, check_package(program, project, obstacles, package)))
    return out


@pytest.mark.parametrize(
    ("name", "plain"), [("cabin", True), ("cabin", False), ("print_path", False)]
)
def test_the_check_misses_no_penetration_the_replay_finds(name: str, plain: bool) -> None:
    found = _replayed(name, plain)
    if plain:  # the comparison means something only where there are contacts
        assert any(replayed for _, replayed, _ in found)
    for program, replayed, contacts in found:
        checked = {(c.element, c.label) for c in contacts}
        deep = {(e, label) for e, label, _, _, d in replayed if d < -SEAT_TOLERANCE - 0.001}
        assert deep <= checked, (program, sorted(deep - checked)[:5])
        assert all(np.isfinite(c.distance) for c in contacts)


@pytest.mark.parametrize("name", list(PACKAGES))
def test_the_replanned_programs_replay_without_a_contact(name: str) -> None:
    for program, replayed, contacts in _replayed(name):
        assert contacts == [], (program, contacts[:3])
        assert replayed == [], (program, replayed[:3])
