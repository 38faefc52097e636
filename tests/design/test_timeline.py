"""When the elements the robot does not build stand: hand work keeps pace with the robot."""

from __future__ import annotations

import numpy as np
from helpers import PROJECTS
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.design.elements import Element, hand_built_stages, structure_timeline
from fabflow.design.generate import generate_elements
from fabflow.project import load_project


def _block(eid: str, z: float, supports: tuple[str, ...], robot: bool) -> Element:
    T = np.eye(4)
    T[2, 3] = z
    return Element(
        eid, "block", T, supports=supports, robot_built=robot, extents=np.array([0.6, 0.1, 0.1])
    )


def test_a_stack_alternating_robot_and_hand() -> None:
    # H0 on the ground, R1 on it, H2 on R1, R3 on H2, H4 on R3 and on R5, which is never built
    elements = [
        _block("H0", 0.05, (), False),
        _block("R1", 0.15, ("H0",), True),
        _block("H2", 0.25, ("R1",), False),
        _block("R3", 0.35, ("H2",), True),
        _block("H4", 0.45, ("R3", "R5"), False),
        _block("R5", 0.35, (), True),
    ]
    stages = hand_built_stages(elements, ["R1", "R3"])
    assert stages == {"H0": 0, "H2": 1, "H4": 0}  # on R5, never built: there all along
    stages = hand_built_stages(elements, ["R5", "R1", "R3"])
    assert stages == {"H0": 0, "H2": 2, "H4": 3}
    timeline = structure_timeline(elements, [["R5", "R1"], ["R3"]])
    (first, coming_first), (second, coming_second) = timeline
    assert [e.id for e in first] == ["H0"]
    assert [(e.id, k) for e, k in coming_first] == [("H2", 1)]  # after R1, the 2nd element
    assert sorted(e.id for e in second) == ["H0", "H2", "R1", "R5"]
    assert [(e.id, k) for e, k in coming_second] == [("H4", 0)]


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_a_hand_element_stands_exactly_when_all_it_rests_on_stands(data) -> None:
    n = data.draw(st.integers(1, 14))
    robot = data.draw(st.lists(st.booleans(), min_size=n, max_size=n))
    elements = []
    for i in range(n):
        below = data.draw(st.lists(st.integers(0, max(i - 1, 0)), max_size=3)) if i else []
        elements.append(_block(f"E{i}", 0.1 * i, tuple(f"E{j}" for j in set(below)), robot[i]))
    order = [e.id for e in elements if e.robot_built]
    order = data.draw(st.permutations(order))
    built = data.draw(st.integers(0, len(order)))
    stages = hand_built_stages(elements, order)
    standing = set(order[:built])
    for e in elements:  # bottom up: a hand element stands when its supports do
        if not e.robot_built and set(e.supports) <= standing:
            standing.add(e.id)
    assert {e for e, k in stages.items() if k <= built} == standing - set(order[:built])


def test_the_cabin_walls_rise_with_the_robot_and_the_gable_comes_last() -> None:
    project = load_project(PROJECTS / "cabin")
    elements = generate_elements(project.elements, project.path)
    robot = [e.id for e in elements if e.robot_built]  # the generator's order: layer by layer
    stages = hand_built_stages(elements, robot)
    by_id = {e.id: e for e in elements}
    hand = [e for e in elements if not e.robot_built]
    assert set(stages) == {e.id for e in hand}  # every one stands once the robot is done
    ground = [e.id for e in hand if by_id[e.id].layer == 0]
    assert ground and all(stages[i] == 0 for i in ground)
    # the front wall's layer above a corner comes once the corner block under it stands
    for e in hand:
        under = [robot.index(s) + 1 for s in e.supports if s in robot]
        if under:
            assert stages[e.id] >= max(under)
    # the prefabricated rear gable is set on the rear wall's top layer, once the robot built it
    gable = [e.id for e in hand if e.attributes["piece"] == "rear_gable"]
    rear = [e for e in elements if e.attributes.get("piece") == "rear"]
    top = max(e.layer for e in rear)
    first_of_top = min(robot.index(e.id) + 1 for e in rear if e.layer == top)
    assert gable and min(stages[g] for g in gable) >= first_of_top


def test_the_order_of_the_elements_does_not_matter() -> None:
    # H1 rests on H2 at the same height, H3 on a cycle with H4, H5 on an unknown id
    elements = [
        _block("H1", 0.15, ("H2",), False),
        _block("H2", 0.15, ("R0",), False),
        _block("R0", 0.05, (), True),
        _block("H3", 0.25, ("H4",), False),
        _block("H4", 0.25, ("H3",), False),
        _block("H5", 0.05, ("nothing",), False),
    ]
    expected = {"H1": 1, "H2": 1, "H3": 0, "H4": 0, "H5": 0}
    assert hand_built_stages(elements, ["R0"]) == expected
    assert hand_built_stages(elements[::-1], ["R0"]) == expected
