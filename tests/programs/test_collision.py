"""Collision check of programs: broad phase, the check, re-planning, the independent replay."""

from __future__ import annotations

import numpy as np
import pytest
from collision_replay import opw_fk, replay
from hypothesis import given, settings
from hypothesis import strategies as st
from program_cases import CASES, PROJECT, make_pose, sample_program
from program_cases import T_WORLD_BASE as CASES_BASE
from program_readers import read_krl, read_rapid

from fabflow.design.elements import Element
from fabflow.errors import InfeasibleError
from fabflow.programs import replan
from fabflow.programs.assemble import compile_program
from fabflow.programs.collision import check_package
from fabflow.programs.collision_model import (
    SLIDE_MARGIN,
    Obstacles,
    environment,
    placements,
    print_path_boxes,
)
from fabflow.programs.collision_phases import Narrow, aabb_pairs
from fabflow.programs.motions import (
    Placement,
    Route,
    Waypoint,
    work_package_motion,
)
from fabflow.programs.replan import (
    candidate_routes,
    checked_program,
    replanned_program,
    with_contacts,
)
from fabflow.programs.writers import writer_for
from fabflow.programs.writers.json_stream import write_json_stream
from fabflow.project import load_project
from fabflow.robots.catalog import get_robot
from fabflow.tasks.targets import T_base_home_tool, block_approach

SIZE = np.array([0.6, 0.105, 0.105])
READERS = {"krl": read_krl, "rapid": read_rapid}
T_WORLD_BASE = make_pose([2.0, 1.0, 0.6])


def _wall(height: float) -> list[Element]:
    """A pre-built wall across the way from the magazine to the places, ``height`` m high."""
    courses = round(height / 0.105)
    return [
        Element(
            f"W{i}{j}",
            "block",
            make_pose([2.9, 0.7 + 0.6 * j, 0.0525 + 0.105 * i]),
            extents=SIZE,
            robot_built=False,
        )
        for i in range(courses)
        for j in range(2)
    ]


def _package() -> list[Element]:
    return [
        Element("B1", "block", make_pose([3.3, 1.0, 0.0525]), extents=SIZE),
        Element("B2", "block", make_pose([3.3, 1.0, 0.1575]), extents=SIZE),
    ]


@pytest.fixture(scope="module")
def project():
    return load_project(PROJECT)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_grid_pairs_are_the_brute_force_pairs(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a_lo = rng.uniform(-3, 3, (40, 3))
    a_hi = a_lo + rng.uniform(0, 1.5, (40, 3))
    b_lo = rng.uniform(-3, 3, (60, 3))
    b_hi = b_lo + rng.uniform(0, 2.5, (60, 3))
    a_lo[3] = np.inf  # an empty box (no held block) pairs with nothing
    a_hi[3] = -np.inf
    ia, ib = aabb_pairs(a_lo, a_hi, b_lo, b_hi, 0.5)
    brute = np.all((a_lo[:, None] <= b_hi[None]) & (a_hi[:, None] >= b_lo[None]), axis=-1)
    assert sorted(zip(ia.tolist(), ib.tolist(), strict=True)) == sorted(
        zip(*np.nonzero(brute), strict=True)
    )


@pytest.mark.parametrize("robot", ["kuka_kr60_3", "abb_irb4600_60_205"])
def test_replay_kinematics_is_the_robot_model(robot: str) -> None:
    model = get_robot(robot)
    rng = np.random.default_rng(4)
    q = rng.uniform(model.joint_limits[:, 0], model.joint_limits[:, 1], (50, 6))
    points, T = opw_fk(robot, q)
    np.testing.assert_allclose(T, model.fk(q), atol=1e-9)
    np.testing.assert_allclose(points["wrist"], model.frames(q)[:, 4, :3, 3], atol=1e-9)


def test_block_approach_clears_the_neighbours(project) -> None:
    block = _package()[0]
    assert block_approach(block, project) >= 0.105 + 2 * project.program.clearance


def test_print_boxes_cover_the_path() -> None:
    t = np.linspace(0, np.pi, 200)
    path = np.c_[np.cos(t), np.sin(t), np.zeros_like(t)]
    element = Element(
        "P",
        "print_path",
        np.eye(4),
        polyline=path,
        attributes={"bead_width": 0.04, "layer_height": 0.02},
    )
    T, ext = print_path_boxes(element)
    local = np.einsum("kji,knj->kni", T[:, :3, :3], path[None] - T[:, None, :3, 3])
    inside = np.all(np.abs(local[..., :2]) <= 0.5 * ext[:, None, :2] + 1e-9, axis=-1).any(axis=0)
    assert inside.all()
    assert np.allclose(T[:, 2, 3], -0.01)
    # made once per element and shared, so no caller may change them
    again = print_path_boxes(element)
    assert again[0] is T and again[1] is ext
    assert not T.flags.writeable and not ext.flags.writeable
    twin = Element("P", "print_path", np.eye(4), polyline=path[::-1].copy(), attributes={})
    assert print_path_boxes(twin)[0] is not T  # an element of the same id is another element


def test_a_wall_in_the_way_is_found_and_the_replay_agrees(project) -> None:
    wall, package = _wall(1.0), _package()
    steps = work_package_motion(package, project, T_WORLD_BASE)
    program = compile_program("t", steps, project, T_WORLD_BASE, {})
    contacts = check_package(
        program, project, environment(project, T_WORLD_BASE, wall, package), package
    )
    assert contacts and {c.element for c in contacts} <= {"B1", "B2"}
    assert any(c.obstacle.startswith("W") and c.distance < 0 for c in contacts)
    stream = next(iter(write_json_stream(program).values()))
    found = replay(stream, [*wall, *package], [w.id for w in wall])
    assert found
    assert {(c[0], c[1]) for c in found} <= {(c.element, c.label) for c in contacts} | {
        (c[0], c[1]) for c in found if c[4] > -0.005
    }


@pytest.mark.parametrize("height", [0.0, 0.6, 1.0])
def test_replanned_programs_replay_without_contacts(project, height: float) -> None:
    wall, package = _wall(height), _package()
    program = checked_program("t", package, wall, project, T_WORLD_BASE, {})
    if height >= 0.6:
        assert "depart" in [m.label for m in program.moves]
    stream = next(iter(write_json_stream(program).values()))
    assert replay(stream, [*wall, *package], [w.id for w in wall]) == []


def test_an_unavoidable_collision_names_element_move_and_body(project) -> None:
    package = _package()[:1]
    roof = [
        Element(
            "R1",
            "block",
            make_pose([3.3, 1.0, 0.2]),
            extents=np.array([0.6, 0.4, 0.05]),
            robot_built=False,
        )
    ]
    _, contacts = replanned_program("t", package, roof, project, T_WORLD_BASE, {})
    assert contacts
    with pytest.raises(InfeasibleError, match=r"element B1, move '.*': the .* R1"):
        checked_program("t", package, roof, project, T_WORLD_BASE, {})


def test_a_clear_program_has_no_contacts_and_the_platform_is_no_obstacle_to_the_base(
    project,
) -> None:
    package = _package()
    steps = work_package_motion(package, project, T_WORLD_BASE)
    program = compile_program("t", steps, project, T_WORLD_BASE, {})
    env = environment(project, T_WORLD_BASE, [], package)
    assert "platform" in set(env.kinds)
    assert check_package(program, project, env, package) == []


def _cover(x: float, length: float, z: float = 0.1575) -> Element:
    """A pre-built block across the first course's place at ``x`` (from above)."""
    return Element(
        f"C{x:.2f}",
        "block",
        make_pose([x, 1.0, z], yaw=np.pi / 2),
        extents=np.array([0.6, length, 0.105]),
        robot_built=False,
    )


def test_a_block_covered_at_one_end_slides_in_and_the_replay_agrees(project) -> None:
    block = _package()[:1]  # x 3.0 .. 3.6, first course
    cover = [_cover(3.55, 0.1)]  # covers x 3.5 .. 3.6 from the second course
    env = environment(project, T_WORLD_BASE, cover, block)
    placed = placements(env, block, project)["B1"]
    clearance = project.program.clearance
    np.testing.assert_allclose(placed.slide, [-(0.1 + 2 * clearance + SLIDE_MARGIN), 0, 0])
    # the descent starts above the cover (its top 0.21 m, the block's bottom at 0)
    assert placed.approach == pytest.approx(0.21 + 2 * clearance + SLIDE_MARGIN)
    program = checked_program("t", block, cover, project, T_WORLD_BASE, {})
    labels = [m.label for m in program.moves]
    assert labels[labels.index("seat") + 1] == "place"
    stream = next(iter(write_json_stream(program).values()))
    assert replay(stream, [*cover, *block], [c.id for c in cover]) == []
    # straight down it would have gone through the cover
    steps = work_package_motion(block, project, T_WORLD_BASE)
    plain = compile_program("t", steps, project, T_WORLD_BASE, {})
    assert any(c.obstacle == cover[0].id for c in check_package(plain, project, env, block))


def test_no_slide_where_the_way_in_is_blocked_or_the_middle_is_covered(project) -> None:
    block = _package()[:1]
    neighbour = Element(
        "N", "block", make_pose([2.7, 1.0, 0.0525]), extents=SIZE, robot_built=False
    )
    for standing in ([_cover(3.55, 0.1), neighbour], [_cover(3.3, 0.1)]):
        env = environment(project, T_WORLD_BASE, standing, block)
        assert placements(env, block, project).get("B1", Placement()).slide is None


@settings(max_examples=50, deadline=None)
@given(st.floats(0.02, 0.25), st.booleans(), st.floats(-np.pi, np.pi), st.floats(0.0, 0.3))
def test_a_slide_clears_what_covers_the_place(project, covered, plus_end, yaw, height) -> None:
    T = make_pose([3.3, 1.0, 0.0525], yaw=yaw)
    block = [Element("B1", "block", T, extents=SIZE)]
    sign = 1.0 if plus_end else -1.0
    centre = T @ np.r_[sign * (0.3 - covered / 2), 0.0, 0.105 + height, 1.0]
    cover = Element(
        "C", "block", make_pose(centre[:3], yaw=yaw), extents=np.array([covered, 0.3, 0.105]),
        robot_built=False,
    )  # fmt: skip
    env = environment(project, T_WORLD_BASE, [cover], block)
    slide = placements(env, block, project)["B1"].slide
    along = float(slide @ T[:3, 0])
    np.testing.assert_allclose(slide, along * T[:3, 0], atol=1e-12)  # along the length
    # lowered beside its place, the block's end keeps twice the clearance from the cover
    gap = abs(along) - covered
    assert np.sign(along) == -sign
    assert gap >= 2 * project.program.clearance - 1e-9


def test_a_tucked_route_turns_at_its_radius_and_starts_by_tucking_in(project) -> None:
    package = _package()
    routes = {"B2": Route(tuck=0.7)}
    steps = [s for s in work_package_motion(package, project, T_WORLD_BASE, routes) if
             isinstance(s, Waypoint)]  # fmt: skip

    def radius(s: Waypoint) -> float:
        return float(np.hypot(*np.linalg.solve(T_WORLD_BASE, s.T_world_tool)[:2, 3]))

    b1 = [s for s in steps if s.element == "B1"]
    b2 = [s for s in steps if s.element == "B2"]
    assert not any("tuck" in s.label for s in b1)
    # B2 draws the tool in from where B1 ended, at B1's height, to its own radius
    assert b2[0].label == "tuck in" and radius(b2[0]) == pytest.approx(0.7)
    assert b2[0].T_world_tool[2, 3] == pytest.approx(b1[-1].T_world_tool[2, 3])
    tuck = next(s for s in b2 if s.label == "tuck")
    pick_up = next(s for s in b2 if s.label == "pick approach")
    assert tuck.kind == "ptp" and radius(tuck) == pytest.approx(0.7)
    assert tuck.T_world_tool[2, 3] >= pick_up.T_world_tool[2, 3] - 1e-12
    assert b2[-2].label == "tuck in" and radius(b2[-2]) == pytest.approx(0.7)
    # the package's last block turns to HOME at its tucked height, then HOME folds it
    over = b2[-1]
    T_home = T_WORLD_BASE @ T_base_home_tool(project)
    assert over.label == "over home" and over.kind == "ptp"
    np.testing.assert_allclose(over.T_world_tool[:2], T_home[:2], atol=1e-12)
    assert over.T_world_tool[2, 3] == pytest.approx(max(T_home[2, 3], b2[-2].T_world_tool[2, 3]))


def test_report_mode_writes_what_still_collides_into_the_program(project) -> None:
    package = _package()[:1]
    roof = [
        Element(
            "R1", "block", make_pose([3.3, 1.0, 0.2]), extents=np.array([0.6, 0.4, 0.05]),
            robot_built=False,
        )
    ]  # fmt: skip
    program, contacts = replanned_program("t", package, roof, project, T_WORLD_BASE, {})
    reported = with_contacts(program, contacts, project.program.clearance)
    assert reported.checks["collision_moves"] == len({c.move for c in contacts}) > 0
    assert "R1" in reported.header["collisions"]
    assert "do not run" in reported.header["collisions"].lower()
    assert len(reported.confirm) == 1 and "collide" in reported.confirm[0]
    for fmt, robot in CASES:  # every writer stops for the operator before the first motion
        sample = with_contacts(sample_program(robot), contacts, project.program.clearance)
        files = writer_for(fmt, robot).write(sample)
        text = "".join(files.values())
        if fmt in READERS:
            before, message = READERS[fmt](files).operator_steps[-1]
            assert before == 0 and sample.confirm[0] in message
        else:
            first_motion = '"setpoint"' if fmt == "json" else "movej("
            assert text.index(sample.confirm[0]) < text.index(first_motion)
    clean = with_contacts(program, [], project.program.clearance)
    assert clean.checks["collision_moves"] == 0 and "collisions" not in clean.header
    assert clean.confirm == ()


@pytest.mark.parametrize("value", [True, False, "report"])
def test_check_collisions_takes_true_false_or_report(project, value) -> None:
    settings_ = project.program.model_validate({"check_collisions": value})
    assert settings_.check_collisions == value


def test_check_collisions_rejects_anything_else(project) -> None:
    with pytest.raises(ValueError, match="check_collisions"):
        project.program.model_validate({"check_collisions": "sometimes"})


def test_a_joint_descent_is_a_seat_move_and_the_replay_agrees(project) -> None:
    # blocks end to end, low in front of the arm, each going down touching the one
    # placed before it: a seat move, whether linear or, past the wrist singularity,
    # a joint move straight down
    course = [
        Element(f"L{i}", "block", make_pose([3.2, 0.2 + 0.6 * i, 0.4], yaw=np.pi / 2),
                extents=SIZE)
        for i in range(3)
    ]  # fmt: skip
    program = checked_program("t", course, [], project, CASES_BASE, {})
    assert program.checks["joint_through_wrist"] >= 1
    stream = next(iter(write_json_stream(program).values()))
    assert replay(stream, course, []) == []
    # a neighbour 5 mm into the place of a block that goes down by a joint move:
    # the seat move touches, it does not penetrate, by the check and by the replay
    held = next(m.element for m in program.moves if m.kind == "ptp" and m.label == "place")
    assert held != course[0].id  # it goes down beside a block placed before it
    T = next(e.T_world_element for e in course if e.id == held).copy()
    T[0, 3] += SIZE[1] - 0.005
    intruder = Element("N", "block", T, extents=SIZE)
    env = environment(project, CASES_BASE, [intruder], course)
    assert (held, "place", "N") in {
        (c.element, c.label, c.obstacle) for c in check_package(program, project, env, course)
    }
    found = replay(stream, [intruder, *course], ["N"])
    assert any(c[:2] == (held, "place") and c[3] == "N" and c[4] < -0.001 for c in found)


def test_a_memo_of_earlier_checks_gives_the_contacts_of_a_fresh_check(project) -> None:
    """Re-planning rounds share a memo: a program whose moves it partly holds (another
    route for one block, the moves after it shifted) has the contacts of a check
    without it, and the moves it already holds are not checked again."""
    wall, package = _wall(1.0), _package()
    obstacles = environment(project, T_WORLD_BASE, wall, package)
    candidates = candidate_routes(package, project, T_WORLD_BASE, obstacles)
    memo: dict = {}
    reused = checked = 0
    for which in ({}, {"B2": 0}, {"B1": 0}, {"B1": 0, "B2": 0}, {"B1": 2}):
        routes = {e: candidates[e][k] for e, k in which.items()}
        steps = work_package_motion(package, project, T_WORLD_BASE, routes)
        try:
            program = compile_program("t", steps, project, T_WORLD_BASE, {})
        except InfeasibleError:
            continue
        fresh = check_package(program, project, obstacles, package)
        before = len(memo)
        got = check_package(program, project, obstacles, package, memo=memo)
        # equal up to rounding: fcl's penetration depth for one pose differs in the
        # last digits with the calls made before it on the same objects
        assert [c.describe() for c in got] == [c.describe() for c in fresh]
        assert [(c.move, c.link, c.obstacle) for c in got] == [
            (c.move, c.link, c.obstacle) for c in fresh
        ]
        np.testing.assert_allclose(
            [c.distance for c in got], [c.distance for c in fresh], rtol=0, atol=1e-12
        )
        checked += 1
        reused += len(program.moves) - (len(memo) - before)
        if not which:
            assert fresh  # the wall is in the way: contacts to carry over
    assert checked >= 3 and reused > 0


def test_routes_asked_for_again_are_not_compiled_again(project, monkeypatch) -> None:
    """The rounds and the final choice often ask for the same route levels: the
    program compiled for them is reused, equal to one compiled afresh, and so is
    the outcome of levels that moved a block on to its next route."""
    wall, package = _wall(1.0), _package()
    obstacles = environment(project, T_WORLD_BASE, wall, package)
    candidates = candidate_routes(package, project, T_WORLD_BASE, obstacles)
    placed = placements(obstacles, package, project)
    compiled: list[str] = []

    def counted(name, *args, **kwargs):
        compiled.append(name)
        return compile_program(name, *args, **kwargs)

    monkeypatch.setattr(replan, "compile_program", counted)

    chains: dict = {}

    def routes(level: dict[str, int], memo: dict, chains: dict = chains):
        return replan._compile_routes(
            "t", package, project, T_WORLD_BASE, {}, candidates, level, placed, {}, memo, chains
        )

    memo: dict = {}
    asked = [{}, {"B1": 0}, {"B1": 0, "B2": 1}, {"B2": len(candidates["B2"])}]
    first = [routes(level, memo) for level in asked]
    count = len(compiled)
    assert count >= len(asked)
    again = [routes(level, memo) for level in asked]
    assert len(compiled) == count
    for a, b, level in zip(first, again, asked, strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            assert b[0] is a[0] and b[1] == a[1]
            b[1]["B1"] = -5  # the caller's copy: the memo keeps its own
            fresh = routes(level, {}, {})
            assert fresh is not None and fresh[1] == a[1]
            assert write_json_stream(fresh[0]) == write_json_stream(a[0])
    assert all(v is None or -5 not in v[1].values() for v in memo.values())


def test_chains_solved_for_other_routes_give_the_programs_of_a_fresh_compile(project) -> None:
    """Re-planning compiles share their solved chains: a program compiled with the
    chains of other routes' programs is, to the bit, the program compiled without
    them, and the chains it shares with them are not solved again."""
    wall, package = _wall(1.0), _package()
    obstacles = environment(project, T_WORLD_BASE, wall, package)
    candidates = candidate_routes(package, project, T_WORLD_BASE, obstacles)
    chains: dict = {}
    reused = compiled = 0
    for which in ({}, {"B2": 0}, {"B1": 0}, {"B1": 0, "B2": 0}, {"B1": 2}, {"B2": 0}):
        routes = {e: candidates[e][k] for e, k in which.items()}
        steps = work_package_motion(package, project, T_WORLD_BASE, routes)
        try:
            fresh = compile_program("t", steps, project, T_WORLD_BASE, {})
        except InfeasibleError:
            with pytest.raises(InfeasibleError):
                compile_program("t", steps, project, T_WORLD_BASE, {}, memo=chains)
            continue
        own: dict = {}
        compile_program("t", steps, project, T_WORLD_BASE, {}, memo=own)
        before = len(chains)
        program = compile_program("t", steps, project, T_WORLD_BASE, {}, memo=chains)
        assert write_json_stream(program) == write_json_stream(fresh)
        assert program.checks == fresh.checks
        after = len(chains)
        reused += len(own) - (after - before)
        again = compile_program("t", steps, project, T_WORLD_BASE, {}, memo=chains)
        assert write_json_stream(again) == write_json_stream(fresh)
        assert len(chains) == after  # every chain found: none solved again
        compiled += 1
    assert compiled >= 4 and reused > 0
    solved = next(iter(chains.values()))
    with pytest.raises(ValueError):  # shared between programs: read-only
        solved.q[0] = 0.0


@pytest.mark.parametrize("length", [0.4, 1.0, 2.0])
def test_the_narrow_phase_capsule_has_its_segments_length(length: float) -> None:
    """A link across a prismatic joint changes length: the capsule fcl measures is the
    segment's at that sample, not the first sample's (the box 1.5 m above the
    capsule's centre, the capsule 0.1 m in radius along z)."""
    box = np.eye(4)
    box[2, 3] = 2.0
    obstacles = Obstacles(
        box[None], np.array([[1.0, 1.0, 1.0]]), np.array(["box"]), np.array(["site"]),
        np.array([""]), np.array([-1]),
    )  # fmt: skip
    narrow = Narrow(obstacles, np.array([0.1]), clearance=2.0)
    for n in (length, 0.7, length):  # another length between: nothing is kept from it
        d = narrow.distance(0, 0, np.eye(3), np.zeros(3), None, n)
    assert d == pytest.approx(1.5 - 0.5 * length - 0.1, abs=1e-5)  # fcl GJK tolerance
