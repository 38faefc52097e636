"""Station planning: targets, reach, stations, build order, work packages, errors."""

from __future__ import annotations

import dataclasses
import itertools
import json

import numpy as np
import pytest
import shapely
from helpers import PROJECTS
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.design.elements import Element
from fabflow.design.generate import generate_elements
from fabflow.errors import InfeasibleError, InputError
from fabflow.project import Project, load_project
from fabflow.robots.catalog import get_robot
from fabflow.robots.reach_model import reach_model
from fabflow.tasks import Plan, planner
from fabflow.tasks.awkward_lifts import SINGULAR_MARGIN_DEG
from fabflow.tasks.cover import tour
from fabflow.tasks.order import (
    assign_passes,
    dissolve_small_visits,
    lift_bands,
    schedule,
    visit_patterns,
)
from fabflow.tasks.planner import make_plan, plan_project
from fabflow.tasks.reachability import thin_frames
from fabflow.tasks.split import split_wide_paths, with_pieces
from fabflow.tasks.stations import _footprints_with_arm, element_polygons, footprint_polygons
from fabflow.tasks.targets import (
    T_base_pick_tool,
    block_approach,
    element_targets,
    element_tool_frames,
)
from fabflow.tasks.verify import unreachable_targets

BLOCK = np.array([0.6, 0.105, 0.105])


@pytest.fixture(scope="module")
def cabin():
    project = load_project(PROJECTS / "cabin" / "project.yaml")
    elements = generate_elements(project.elements, project.path)
    return project, elements, make_plan(project, elements)


def small_project(obstacles=(), **planning) -> Project:
    """A 12 x 12 m site with the default robot and platform."""
    return Project.model_validate(
        {
            "name": "synthetic",
            "site": {
                "extent_min": [-4.0, -4.0],
                "extent_max": [8.0, 8.0],
                "obstacles": list(obstacles),
            },
            "robot": {
                "tool": {"T_flange_tool": {"xyz": [0, 0, 0.25]}},
                "platform": {"lift": [0.0, 1.5], "T_platform_base": {"xyz": [0.3, 0, 0.6]}},
            },
            "elements": [{"task_points": [{"id": "unused", "pose": {}}]}],
            "planning": planning,
        }
    )


def block(bid: str, x: float, y: float, layer: int, supports=(), heading=0.0) -> Element:
    T = np.eye(4)
    c, s = np.cos(heading), np.sin(heading)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x, y, (layer + 0.5) * BLOCK[2])
    return Element(
        id=bid,
        type="block",
        T_world_element=T,
        layer=layer,
        supports=tuple(supports),
        extents=BLOCK,
    )


def running_bond_wall(n: int, layers: int, x0: float = 0.0, y: float = 0.0) -> list[Element]:
    """A straight wall along x: n blocks per layer, odd layers shifted by half a block."""
    out: list[Element] = []
    for k in range(layers):
        shift = 0.3 if k % 2 else 0.0
        for i in range(n - (k % 2)):
            x = x0 + 0.3 + 0.6 * i + shift
            sup = []
            if k:
                sup = [
                    e.id
                    for e in out
                    if e.layer == k - 1 and abs(e.T_world_element[0, 3] - x) < 0.59
                ]
            out.append(block(f"W{k:02d}_{i:02d}", x, y, k, sup))
    return out


# ------------------------------------------------------------------ the cabin


def test_cabin_every_robot_built_element_once(cabin):
    _, elements, plan = cabin
    planned = [e for wp in plan.work_packages for e in wp.elements]
    robot_built = {e.id for e in elements if e.robot_built}
    assert len(planned) == len(set(planned))
    assert set(planned) == robot_built


def test_cabin_targets_are_block_top_centres_tool_down(cabin):
    _, elements, plan = cabin
    by_id = {e.id: e for e in elements}
    for wp in plan.work_packages:
        assert wp.T_world_targets.shape == (len(wp.elements), 4, 4)
        for eid, T in zip(wp.elements, wp.T_world_targets, strict=True):
            e = by_id[eid]
            top = e.T_world_element[:3, 3] + e.T_world_element[:3, 2] * e.extents[2] / 2
            np.testing.assert_allclose(T[:3, 3], top, atol=1e-12)
            np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)
            np.testing.assert_allclose(T[:3, 0], e.T_world_element[:3, 0], atol=1e-12)
            np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)


def test_cabin_every_target_has_an_ik_solution(cabin):
    project, _, plan = cabin
    assert unreachable_targets(plan, project) == []
    assert plan.summary["ik_unreachable"] == []


def test_cabin_footprints_collide_with_nothing_present(cabin):
    project, elements, plan = cabin
    platform = project.robot.platform
    geoms = element_polygons(elements)
    gid = {e.id: g for e, g in zip(elements, geoms, strict=True)}
    present = [g for e, g in zip(elements, geoms, strict=True) if not e.robot_built]
    obstacles = [shapely.box(*o.box.min[:2], *o.box.max[:2]) for o in project.site.obstacles]
    site = shapely.box(*project.site.extent_min, *project.site.extent_max)
    for wp in plan.work_packages:
        T = wp.station.T_world_platform
        fp = footprint_polygons(
            T[None, :2, 3],
            np.array([np.arctan2(T[1, 0], T[0, 0])]),
            platform.footprint,
            platform.safety_margin,
        )[0]
        present += [gid[e] for e in wp.elements]
        assert site.contains(fp)
        assert not any(fp.intersects(o) for o in obstacles)
        assert not any(fp.intersects(g) for g in present), wp.station.id


def test_cabin_supports_hold_across_the_sequence(cabin):
    _, elements, plan = cabin
    position = {e: i for i, e in enumerate(e for wp in plan.work_packages for e in wp.elements)}
    prebuilt = {e.id for e in elements if not e.robot_built}
    n_checked = 0
    for e in elements:
        if not e.robot_built:
            continue
        for s in e.supports:
            assert s in prebuilt or position[s] < position[e.id], (s, e.id)
            n_checked += 1
    assert n_checked > 500


def test_cabin_summary_and_station_count(cabin):
    project, _, plan = cabin
    s = plan.summary
    k = s["stations"]
    assert k == len(plan.stations) == len(s["elements_per_station"])
    assert k >= s["station_lower_bound"] >= 3
    assert sum(s["elements_per_station"].values()) == s["elements"]
    assert s["visits"] >= k
    assert s["travel_m"] == pytest.approx(sum(wp.travel for wp in plan.work_packages), abs=1e-3)
    if k > 3:
        # The plan says why it needs more than the paper's three stations.
        assert any("share no" in n for n in plan.notes)
    ids = [wp.station.id for wp in plan.work_packages]
    assert ids[0] == "S1"
    for wp in plan.work_packages:
        lo, hi = project.robot.platform.lift
        assert lo - 1e-9 <= wp.station.lift <= hi + 1e-9


def test_plan_json_round_trip(cabin):
    _, _, plan = cabin
    d = json.loads(json.dumps(plan.to_dict()))
    back = Plan.from_dict(d)
    assert [wp.elements for wp in back.work_packages] == [wp.elements for wp in plan.work_packages]
    for a, b in zip(back.work_packages, plan.work_packages, strict=True):
        np.testing.assert_allclose(a.T_world_targets, b.T_world_targets)
        np.testing.assert_allclose(a.station.T_world_platform, b.station.T_world_platform)
        assert a.station.id == b.station.id and a.station.lift == b.station.lift


# ------------------------------------------------------------- synthetic cases


def test_short_wall_needs_one_station_and_one_visit():
    project = small_project()
    wall = running_bond_wall(4, 6)
    plan = plan_project(project, wall)
    assert plan.summary["stations"] == 1
    assert plan.summary["visits"] == 1
    order = [e for wp in plan.work_packages for e in wp.elements]
    layers = [int(e[1:3]) for e in order]
    assert layers == sorted(layers)


def test_long_wall_is_split_and_supports_hold():
    project = small_project()
    wall = running_bond_wall(12, 8, x0=-2.0)  # 7.2 m: more than one station can reach
    plan = plan_project(project, wall)
    assert plan.summary["stations"] >= 2
    pos = {e: i for i, e in enumerate(e for wp in plan.work_packages for e in wp.elements)}
    assert set(pos) == {e.id for e in wall}
    for e in wall:
        assert all(pos[s] < pos[e.id] for s in e.supports)
    assert unreachable_targets(plan, project) == []


def test_element_far_outside_the_site_is_reported():
    project = small_project()
    elements = [*running_bond_wall(3, 2), block("FAR", 30.0, 30.0, 0)]
    with pytest.raises(InfeasibleError) as exc:
        plan_project(project, elements)
    assert "FAR" in str(exc.value) and "W00_00" not in str(exc.value)
    assert "site extent" in str(exc.value)


def test_element_too_high_is_reported():
    project = small_project()
    elements = [*running_bond_wall(3, 2), block("HIGH", 1.0, 0.0, 60)]
    with pytest.raises(InfeasibleError, match=r"HIGH.*height"):
        plan_project(project, elements)


def test_element_surrounded_by_an_obstacle_is_reported():
    fence = {"box": {"name": "fence", "min": [-3, -3, 0], "max": [3, 3, 2]}}
    project = small_project(obstacles=[fence])
    with pytest.raises(InfeasibleError, match=r"B1.*collides with obstacle 'fence'"):
        plan_project(project, [block("B1", 0.0, 0.0, 0)])


def test_support_cycle_is_reported():
    project = small_project()
    a = block("A", 0.5, 0.0, 0, supports=["C"])
    b = block("B", 0.5, 0.0, 1, supports=["A"])
    c = block("C", 0.5, 0.0, 2, supports=["B"])
    with pytest.raises(InfeasibleError, match=r"cycle.*(A|B|C) -> "):
        plan_project(project, [a, b, c])


def test_unknown_support_and_repeated_id_are_input_errors():
    project = small_project()
    with pytest.raises(InputError, match="'NOPE'"):
        plan_project(project, [block("A", 0.5, 0.0, 0, supports=["NOPE"])])
    with pytest.raises(InputError, match="unique"):
        plan_project(project, [block("A", 0.5, 0.0, 0), block("A", 1.5, 0.0, 0)])


def test_max_stations_is_enforced():
    project = small_project(max_stations=1)
    with pytest.raises(InfeasibleError, match="max_stations is 1"):
        plan_project(project, running_bond_wall(12, 2, x0=-2.0))


def test_prebuilt_elements_only_gives_an_empty_plan():
    project = small_project()
    wall = [dataclasses.replace(e, robot_built=False) for e in running_bond_wall(3, 2)]
    plan = plan_project(project, wall)
    assert plan.work_packages == () and plan.summary["stations"] == 0


def test_prebuilt_support_counts_as_present():
    project = small_project()
    base = dataclasses.replace(block("BASE", 1.0, 0.0, 0), robot_built=False)
    top = block("TOP", 1.0, 0.0, 1, supports=["BASE"])
    plan = plan_project(project, [base, top])
    assert [e for wp in plan.work_packages for e in wp.elements] == ["TOP"]


# ----------------------------------------------------------------- components


def test_reach_model_is_conservative_against_ik():
    from fabflow.robots import get_robot

    project = small_project()
    T_flange_tool = project.robot.tool.T_flange_tool.matrix()
    reach = reach_model("kuka_kr60_3", T_flange_tool)
    assert reach.source == "ik"
    rng = np.random.default_rng(1)
    i, j = np.nonzero(reach.table)
    pick = rng.choice(len(i), 400, replace=False)
    r = (i[pick] + rng.uniform(0, 1, 400)) * reach.r_step
    z = reach.z_min + (j[pick] + rng.uniform(0, 1, 400)) * reach.z_step
    yaw = rng.uniform(-np.pi, np.pi, 400)
    T = np.repeat(np.eye(4)[None], 400, axis=0)
    T[:, :3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = r * np.cos(yaw), r * np.sin(yaw), z
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.zeros((400, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1
    T[:, :3, :3] = Rz @ T[:, :3, :3]
    _, valid = get_robot("kuka_kr60_3").ik_batch(T @ np.linalg.inv(T_flange_tool))
    assert valid.any(axis=1).all()
    assert reach.reachable_base(T[:, :3, 3]).all()
    assert not reach.reachable(np.array([reach.r_max + 0.1]), np.array([0.0]))[0]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 12))
def test_level_masks_are_reachable_at_every_height(seed: int, levels: int) -> None:
    """The per-row masks equal :meth:`reachable` point by point, inside, on and beyond
    the table's edges."""
    reach = reach_model("kuka_kr60_3", small_project().robot.tool.T_flange_tool.matrix())
    rng = np.random.default_rng(seed)
    rows = int(rng.integers(1, 6))
    z = rng.uniform(reach.z_min - 0.5, reach.z_min + reach.table.shape[1] * reach.z_step + 0.5,
                    (rows, levels))  # fmt: skip
    z[0, 0] = reach.z_min  # a cell edge
    frame = rng.integers(0, rows, 200)
    r = rng.uniform(-0.1, reach.r_max + 0.3, 200)
    r[:3] = [0.0, reach.r_step, reach.r_max]
    expected = (reach.reachable(r[:, None], z[frame]) << np.arange(levels)).sum(axis=1)
    assert np.array_equal(reach.level_masks(r, frame, z), expected)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.05, 1.5))
def test_footprints_with_the_arm_are_the_unions_one_by_one(seed: int, radius: float) -> None:
    """Unions made once per heading and moved equal the footprint joined with the disc
    about each base (up to rounding of the moved vertices)."""
    platform = small_project().robot.platform
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-20.0, 20.0, (25, 2))
    heading = np.radians(rng.choice([0.0, 45.0, 90.0, 180.0, 270.0], 25))
    off = platform.T_platform_base.matrix()[:2, 3]
    c, s = np.cos(heading), np.sin(heading)
    offset = np.stack([c * off[0] - s * off[1], s * off[0] + c * off[1]], axis=1)
    got = _footprints_with_arm(xy, heading, offset, platform.footprint, 0.1, radius)
    base = xy + offset
    expected = shapely.union(
        footprint_polygons(xy, heading, platform.footprint, 0.1),
        shapely.buffer(shapely.points(base), radius, quad_segs=8),
    )
    assert (shapely.hausdorff_distance(got, expected) < 1e-9).all()
    assert (shapely.area(shapely.symmetric_difference(got, expected)) < 1e-9).all()


def test_fallback_reach_model_is_close_to_ik():
    T_flange_tool = np.eye(4)
    T_flange_tool[2, 3] = 0.25
    ik = reach_model("kuka_kr60_3", T_flange_tool)
    geo = reach_model("kuka_kr60_3", T_flange_tool, use_ik=False)
    assert geo.source == "geometric"
    assert abs(geo.r_max - ik.r_max) < 0.1
    both = (ik.table & geo.table).sum()
    assert both / geo.table.sum() > 0.9


def test_element_targets_of_task_point_and_rotated_block():
    T = np.eye(4)
    T[:3, 3] = (1, 2, 3)
    tp = Element(id="T", type="task_point", T_world_element=T)
    b = block("B", 0.0, 0.0, 0, heading=np.pi / 2)
    out = element_targets([tp, b])
    np.testing.assert_allclose(out[0], T)
    np.testing.assert_allclose(out[1][:3, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(out[1][:3, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(out[1][:3, 3], [0, 0, BLOCK[2]], atol=1e-12)


@settings(deadline=None, max_examples=60)
@given(st.lists(st.integers(1, 15), min_size=1, max_size=12))
def test_lift_bands_uses_reachable_levels_with_fewest_changes(masks):
    masks = np.array(masks, dtype=np.int64)
    levels = lift_bands(masks)
    assert all((m >> int(lv)) & 1 for m, lv in zip(masks, levels, strict=True))
    # Dynamic program for the true minimum number of changes.
    inf = 10**9
    best = [0 if (masks[0] >> lv) & 1 else inf for lv in range(4)]
    for m in masks[1:]:
        low = min(best)
        best = [min(best[lv], low + 1) if (m >> lv) & 1 else inf for lv in range(4)]
    assert int(np.count_nonzero(np.diff(levels))) == min(best)


@settings(deadline=None, max_examples=40)
@given(st.integers(0, 2**32 - 1), st.integers(1, 5))
def test_assign_passes_respects_reach_and_supports(seed, k):
    rng = np.random.default_rng(seed)
    n = 30
    src_l, dst_l = [], []
    for e in range(1, n):
        for s in rng.choice(e, size=min(e, int(rng.integers(0, 3))), replace=False):
            src_l.append(int(s))
            dst_l.append(e)
    src, dst = np.array(src_l, dtype=np.intp), np.array(dst_l, dtype=np.intp)
    reach_sets = [
        np.sort(rng.choice(k, size=int(rng.integers(1, k + 1)), replace=False)) for _ in range(n)
    ]
    for pattern in visit_patterns(k).values():
        visit = assign_passes(reach_sets, src, dst, np.arange(n), pattern)
        station = pattern[visit % len(pattern)]
        assert all(station[e] in reach_sets[e] for e in range(n))
        assert (visit[src] <= visit[dst]).all()
        # Least assignment: no element could go to an earlier visit.
        for e in range(n):
            need = visit[src[dst == e]].max() if (dst == e).any() else 0
            earlier = [
                p for p in range(need, visit[e]) if pattern[p % len(pattern)] in reach_sets[e]
            ]
            assert not earlier
        # Dissolving small visits keeps both properties and never adds visits.
        after = dissolve_small_visits(
            visit,
            pattern[np.arange(visit.max() + 1) % len(pattern)],
            reach_sets,
            src,
            dst,
            np.zeros(n, dtype=bool),
        )
        station2 = pattern[after % len(pattern)]
        assert all(station2[e] in reach_sets[e] for e in range(n))
        assert (after[src] <= after[dst]).all()
        assert len(np.unique(after)) <= len(np.unique(visit))


def test_schedule_builds_blocked_elements_after_the_station_leaves():
    # Element 2 lies under station 0's footprint: built only once station 0 is done.
    visit = np.array([0, 0, 1, 1])
    visit_station = np.array([0, 1])
    layer = np.array([0, 1, 0, 1])
    p = np.zeros((4, 3))
    src, dst = np.array([2], dtype=np.intp), np.array([3], dtype=np.intp)
    blocked = [np.array([2]), np.array([], dtype=np.intp)]
    vs = schedule(visit, visit_station, layer, p, src, dst, blocked, ["a", "b", "c", "d"])
    assert [v.station for v in vs] == [0, 1]
    assert list(vs[0].elements) == [0, 1] and list(vs[1].elements) == [2, 3]
    # A station whose own element rests on something under its footprint cannot work.
    src2, dst2 = np.array([2], dtype=np.intp), np.array([1], dtype=np.intp)
    with pytest.raises(InfeasibleError, match="footprint of station S1"):
        schedule(visit, visit_station, layer, p, src2, dst2, blocked, ["a", "b", "c", "d"])


def test_tour_is_a_short_permutation():
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 10, (9, 2))
    order = tour(xy, start=np.zeros(2))
    assert sorted(order.tolist()) == list(range(9))
    length = np.hypot(*np.diff(xy[order], axis=0).T).sum()
    ident = np.hypot(*np.diff(xy, axis=0).T).sum()
    assert length <= ident + 1e-9


def print_layers(length: float, n_layers: int, y: float = 0.0) -> list[Element]:
    """A straight printed wall along x: one print path element per 2 cm layer."""
    out = []
    x = np.linspace(-0.5 * length, 0.5 * length, 200)
    for k in range(n_layers):
        T = np.eye(4)
        T[:3, 3] = (1.0, y, 0.02 * (k + 1))
        out.append(
            Element(
                id=f"P{k:03d}",
                type="print_path",
                T_world_element=T,
                layer=k,
                supports=() if k == 0 else (f"P{k - 1:03d}",),
                polyline=np.c_[x, np.zeros_like(x), np.zeros_like(x)],
                attributes={"bead_width": 0.04, "extrude": [True] * 199},
            )
        )
    return out


def test_split_pieces_cover_the_path_and_stack():
    layers = print_layers(5.0, 3)
    out, pieces = split_wide_paths(layers, 0.7)
    assert set(pieces) == {"P000", "P001", "P002"}
    n = len(pieces["P000"])
    assert n >= 3 and all(len(v) == n for v in pieces.values())
    by_id = {e.id: e for e in out}
    for k in range(n):
        piece = by_id[f"P001.{k + 1}"]
        # on its own stretch and its neighbours' below: they meet at the seams
        assert piece.supports == tuple(f"P000.{j + 1}" for j in range(max(k - 1, 0), min(k + 2, n)))
        a, b = piece.attributes["waypoints"]
        np.testing.assert_allclose(piece.polyline, layers[1].polyline[a : b + 1])
        assert len(piece.attributes["extrude"]) == len(piece.polyline) - 1
    ranges = [by_id[p].attributes["waypoints"] for p in pieces["P000"]]
    assert ranges[0][0] == 0 and ranges[-1][1] == 199
    assert all(r[1] == s[0] for r, s in itertools.pairwise(ranges))
    assert with_pieces(layers, [by_id[p] for ids in pieces.values() for p in ids]) == out


def test_wide_print_path_is_planned_in_pieces():
    project = small_project()
    layers = print_layers(5.0, 4)
    plan = plan_project(project, layers)
    planned = [e for wp in plan.work_packages for e in wp.elements]
    pieces = {e.id for e in plan.split_elements}
    assert sorted(planned) == sorted(pieces)
    assert {e.attributes["parent"] for e in plan.split_elements} == {e.id for e in layers}
    pos = {e: i for i, e in enumerate(planned)}
    for e in plan.split_elements:
        assert all(pos[s] < pos[e.id] for s in e.supports)
    assert plan.summary["stations"] >= 2
    assert any("split" in n for n in plan.notes)
    assert unreachable_targets(plan, project) == []
    back = Plan.from_dict(json.loads(json.dumps(plan.to_dict())))
    assert [e.id for e in back.split_elements] == [e.id for e in plan.split_elements]


def test_thin_frames_keeps_ends_and_spacing():
    p = np.r_[np.c_[np.linspace(0, 1, 101), np.zeros((101, 2))]]
    p = np.r_[p, p]
    owner = np.r_[np.zeros(101, int), np.ones(101, int)]
    keep = thin_frames(p, owner, 0.05)
    assert keep[[0, 100, 101, 201]].all()
    for o in (0, 1):
        x = p[keep & (owner == o), 0]
        assert np.diff(x).max() <= 0.05 + 0.011
    assert keep.sum() < 60


def test_plan_stage_hands_the_pieces_to_later_stages(tmp_path):
    from fabflow.build.context import BuildContext
    from fabflow.build.plan import stage_plan

    ctx = BuildContext(project=small_project(), out=tmp_path)
    ctx.elements = print_layers(5.0, 2)
    stage_plan(ctx)
    plan = ctx.plan
    assert plan.split_elements
    ids = {e.id for e in ctx.elements}
    assert ids == {e.id for e in plan.split_elements}
    assert all(e in ids for wp in plan.work_packages for e in wp.elements)
    data = json.loads((tmp_path / "plan.json").read_text())
    assert len(data["split_elements"]) == len(plan.split_elements)


def test_tilted_task_points_are_planned_with_ik():
    project = small_project()
    elements = []
    for i, (x, y) in enumerate([(0.0, 0.0), (2.0, 1.0), (-1.0, 2.5)]):
        T = np.eye(4)
        # Tool z horizontal (along world +x), e.g. drilling into a wall face.
        T[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
        T[:3, 3] = (x, y, 1.2)
        elements.append(Element(id=f"D{i}", type="task_point", T_world_element=T))
    plan = plan_project(project, elements)
    assert sorted(e for wp in plan.work_packages for e in wp.elements) == ["D0", "D1", "D2"]
    assert unreachable_targets(plan, project) == []
    assert not any("position only" in n for n in plan.notes)


def test_narrow_site_parks_on_ground_built_later():
    # The site is one platform wide, so the platform must stand where blocks go.
    project = Project.model_validate(
        {
            **small_project().model_dump(exclude={"path"}),
            "site": {"extent_min": [-4.0, -1.25], "extent_max": [7.0, 1.25], "obstacles": []},
        }
    )
    wall = [block(f"W{i}", 0.3 + 0.6 * i, 0.0, 0) for i in range(5)]
    plan = plan_project(project, wall)
    assert any("stand where robot-built elements go" in n for n in plan.notes)
    platform = project.robot.platform
    outline = dict(zip([e.id for e in wall], element_polygons(wall), strict=True))
    built: list[str] = []
    for wp in plan.work_packages:
        T = wp.station.T_world_platform
        fp = footprint_polygons(
            T[None, :2, 3],
            np.array([np.arctan2(T[1, 0], T[0, 0])]),
            platform.footprint,
            platform.safety_margin,
        )[0]
        built += wp.elements
        assert not any(fp.intersects(outline[e]) for e in built)
    assert sorted(built) == sorted(e.id for e in wall)


def _singular_descents(project, plan, elements) -> int:
    """Planned blocks whose straight descent takes A5 through 0, or within the margin of
    it, on every branch that follows it and reaches the magazine (computed here from the
    plan)."""
    robot = get_robot(project.robot.model)
    T_tool_flange = np.linalg.inv(project.robot.tool.T_flange_tool.matrix())
    T_platform_base = project.robot.platform.T_platform_base.matrix()
    _, at_pick = robot.ik_batch((T_base_pick_tool(project) @ T_tool_flange)[None])
    by_id = {e.id: e for e in elements}
    count = 0
    for wp in plan.work_packages:
        T_base_world = np.linalg.inv(wp.station.T_world_base(T_platform_base))
        for eid in wp.elements:
            e = by_id[eid]
            T = np.repeat(element_tool_frames(e)[:1], 9, axis=0)
            T[:, 2, 3] += np.linspace(0.0, block_approach(e, project), 9)
            q, valid = robot.ik_batch(T_base_world @ T @ T_tool_flange)
            usable = valid.all(axis=0) & at_pick[0]
            a5 = q[:, :, 4]
            clear = (np.abs(a5) >= np.radians(SINGULAR_MARGIN_DEG)).all(axis=0)
            clear &= (np.sign(a5) == np.sign(a5[:1])).all(axis=0)
            count += bool(usable.any() and not (usable & clear).any())
    return count


def test_the_lift_keeps_block_descents_off_the_wrist_singularity(cabin, monkeypatch):
    project, elements, plan = cabin
    preferred = _singular_descents(project, plan, elements)
    monkeypatch.setattr(planner, "_regular_reach", lambda project, A_ch, *args: A_ch)
    plain = plan_project(project, elements)
    before = _singular_descents(project, plain, elements)
    assert len(plan.work_packages) > len(plain.work_packages)  # more lift changes
    # 1 of 548 against 29: B0031, singular at every level of every station reaching it
    assert preferred <= 1 < before / 10, (preferred, before)
