"""The parametric cabin, the supports relation, generate_elements and the design stage."""

from __future__ import annotations

import itertools
import json
import math
import pickle
import shutil
import time

import ezdxf
import numpy as np
import pytest
from helpers import PROJECTS
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.build.context import BuildContext
from fabflow.build.design import stage_design
from fabflow.design.cabin import cabin_block_bound, cabin_blocks, cabin_layer_counts
from fabflow.design.elements import (
    Element,
    Standing,
    element_boxes,
    elements_from_json,
    elements_to_json,
)
from fabflow.design.generate import generate_elements
from fabflow.design.specs import BlockSize, CabinSpec, Opening
from fabflow.design.supports import compute_supports, max_overlap_volume
from fabflow.errors import InputError
from fabflow.project import parse_project

DEFAULT = CabinSpec()


@pytest.fixture(scope="module")
def blocks():
    return cabin_blocks(DEFAULT)


def _wall_coords(b, spec: CabinSpec):
    """Along-wall start/end and bottom/top of every block, in the cabin frame."""
    along_x = np.isin(b.wall, ["left", "right"])
    centre = b.T_world_block[:, :3, 3] - np.asarray(spec.origin)
    s = np.where(along_x, centre[:, 0], centre[:, 1])
    half = b.extents[:, 0] / 2
    z0 = centre[:, 2] - b.extents[:, 2] / 2
    return s - half, s + half, z0, z0 + b.extents[:, 2]


def test_default_cabin_reproduces_paper_counts(blocks) -> None:
    total, robot = len(blocks), int(blocks.robot_built.sum())
    assert abs(total - 737) / 737 < 0.10, total
    assert abs(robot - 536) / 536 < 0.10, robot
    assert set(np.unique(blocks.part[blocks.robot_built])) == {"A", "B", "C"}
    assert set(np.unique(blocks.part[~blocks.robot_built])) == {"front", "rear"}
    assert np.unique(blocks.layer[blocks.robot_built]).tolist() == list(range(30))
    assert blocks.layer.max() + 1 == 40  # 4.20 m / 0.105 m


def test_blocks_have_paper_size_and_are_cut_only_at_row_ends(blocks) -> None:
    L = DEFAULT.block.length
    plain = blocks.kind == "block"
    assert np.all(blocks.extents[plain, 0] <= L + 1e-9)
    assert np.mean(np.isclose(blocks.extents[plain, 0], L)) > 0.5
    assert np.allclose(blocks.extents[:, 1:], [DEFAULT.block.width, DEFAULT.block.height])


def test_no_block_floats_and_none_overlap(blocks) -> None:
    sup = compute_supports(blocks.T_world_block, blocks.extents)
    bottoms = blocks.T_world_block[:, 2, 3] - blocks.extents[:, 2] / 2
    on_ground = np.isclose(bottoms, DEFAULT.origin[2])
    assert np.array_equal(on_ground, blocks.layer == 0)
    floating = [i for i in range(len(blocks)) if not on_ground[i] and len(sup[i]) == 0]
    assert floating == []
    for i in np.flatnonzero(blocks.layer > 0)[::7]:
        assert np.all(blocks.layer[sup[i]] == blocks.layer[i] - 1)
    assert max_overlap_volume(blocks.T_world_block, blocks.extents) <= 1e-6


def test_corners_cross_like_a_log_cabin(blocks) -> None:
    t = DEFAULT.block.width
    centre = blocks.T_world_block[:, :3, 3]
    ext_x = np.where(np.isin(blocks.wall, ["left", "right"]), blocks.extents[:, 0], t)
    ext_y = np.where(np.isin(blocks.wall, ["left", "right"]), t, blocks.extents[:, 0])
    # which block covers the corner square at the origin, per layer
    covers = (np.abs(centre[:, 0] - t / 2) <= ext_x / 2 - t / 2 + 1e-9) & (
        np.abs(centre[:, 1] - t / 2) <= ext_y / 2 - t / 2 + 1e-9
    )
    n_wall, _ = cabin_layer_counts(DEFAULT)
    for k in range(n_wall):
        owners = blocks.wall[covers & (blocks.layer == k)]
        assert owners.tolist() == (["right"] if k % 2 == 0 else ["front"])


def test_joints_are_staggered_between_layers(blocks) -> None:
    s0, s1, _, _ = _wall_coords(blocks, DEFAULT)
    worst = np.inf
    for wall in ("front", "rear", "left", "right"):
        for k in range(int(blocks.layer.max())):
            j = []
            for kk in (k, k + 1):
                m = (blocks.wall == wall) & (blocks.layer == kk)
                ends = np.round(np.concatenate([s0[m], s1[m]]), 9)
                u, c = np.unique(ends, return_counts=True)
                j.append(u[c == 2])  # where two pieces of the row meet
            if len(j[0]) and len(j[1]):
                worst = min(worst, np.abs(j[0][:, None] - j[1][None, :]).min())
    assert worst >= 0.05


def test_openings_are_left_open_with_lintels(blocks) -> None:
    s0, s1, z0, z1 = _wall_coords(blocks, DEFAULT)
    h = DEFAULT.block.height
    for o in DEFAULT.openings:
        on_wall = blocks.wall == o.wall
        lo, hi = o.center - o.width / 2, o.center + o.width / 2
        inside = (
            on_wall
            & (s0 < hi - 1e-9)
            & (s1 > lo + 1e-9)
            & (z0 < o.sill + o.height - 1e-9)
            & (z1 > o.sill + 1e-9)
        )
        assert not inside.any()
        lintel_layer = math.ceil((o.sill + o.height) / h - 1e-6)
        lintel = on_wall & (blocks.kind == "lintel") & (blocks.layer == lintel_layer)
        lintel &= (s0 < lo) & (s1 > hi)
        assert lintel.sum() == 1
        assert np.isclose((s1 - s0)[lintel][0], o.width + 2 * DEFAULT.lintel_bearing)


def test_gables_step_in_towards_the_ridge(blocks) -> None:
    n_wall, n_total = cabin_layer_counts(DEFAULT)
    front = blocks.piece == "front_gable"
    widths = [blocks.extents[front & (blocks.layer == k), 0].sum() for k in range(n_wall, n_total)]
    assert all(a > b for a, b in itertools.pairwise(widths))
    assert not np.isin(blocks.wall[blocks.layer >= n_wall], ["left", "right"]).any()


def test_origin_and_heading_move_the_whole_cabin(blocks) -> None:
    moved = cabin_blocks(CabinSpec(origin=(2.0, -1.0, 0.5), heading_deg=90.0))
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = [2.0, -1.0, 0.5]
    assert np.allclose(moved.T_world_block, T @ blocks.T_world_block)


def test_bad_openings_name_the_field() -> None:
    text = """
name: bad
elements:
  - cabin:
      openings:
        - {wall: left, center: 0.2, width: 0.9, height: 1.0}
"""
    with pytest.raises(InputError) as err:
        parse_project(text, "bad.yaml")
    msg = str(err.value)
    assert "elements[0].cabin" in msg and "openings[0]" in msg and "line 5" in msg
    with pytest.raises(ValueError, match="overlap"):
        CabinSpec(
            openings=[
                Opening(wall="rear", center=1.0, width=0.6, height=1.0),
                Opening(wall="rear", center=1.7, width=0.6, height=1.0),
            ]
        )


@st.composite
def stacked_boxes(draw):
    n = draw(st.integers(2, 25))
    x = draw(st.lists(st.integers(0, 6), min_size=n, max_size=n))
    y = draw(st.lists(st.integers(0, 3), min_size=n, max_size=n))
    k = draw(st.lists(st.integers(0, 3), min_size=n, max_size=n))
    yaw = draw(st.lists(st.sampled_from([0.0, 90.0, 30.0]), min_size=n, max_size=n))
    return np.array(x) * 0.3, np.array(y) * 0.3, np.array(k), np.radians(yaw)


@settings(deadline=None, max_examples=40)
@given(stacked_boxes())
def test_supports_match_brute_force(boxes) -> None:
    import shapely

    x, y, k, yaw = boxes
    n = len(x)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = (
        np.cos(yaw),
        -np.sin(yaw),
        np.sin(yaw),
        np.cos(yaw),
    )
    T[:, :3, 3] = np.column_stack([x, y, (k + 0.5) * 0.1])
    ext = np.tile([0.6, 0.2, 0.1], (n, 1))
    sup = compute_supports(T, ext)
    for i in range(n):
        expected = []
        for j in range(n):
            if i == j or k[j] != k[i] - 1:
                continue
            a = shapely.Polygon(_rect(T[i], ext[i]))
            b = shapely.Polygon(_rect(T[j], ext[j]))
            if a.intersection(b).area > 1e-6:
                expected.append(j)
        assert sup[i].tolist() == expected


def _rect(T: np.ndarray, e: np.ndarray) -> np.ndarray:
    local = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * e[:2] / 2
    return local @ T[:2, :2].T + T[:2, 3]


PROJECT = """
name: mixed
elements:
  - cabin: {{}}
  - print_path:
      dxf: {dxf}
      layers: [WALL_OUTER]
      n_layers: 3
  - task_points:
      - {{id: drill-1, pose: {{xyz: [1.0, 2.0, 0.5], abc_deg: [0, 180, 0]}}, action: drill,
         params: {{depth: 0.05}}}}
      - {{id: mark-1, pose: {{xyz: [2.0, 2.0, 0.0]}}, layer: 2}}
"""


@pytest.fixture(scope="module")
def mixed_project(tmp_path_factory):

    folder = tmp_path_factory.mktemp("mixed")
    shutil.copy(PROJECTS / "print_path" / "sine_wall.dxf", folder)
    return parse_project(PROJECT.format(dxf="sine_wall.dxf"), folder / "project.yaml", folder)


@pytest.fixture(scope="module")
def mixed_elements(mixed_project):
    return generate_elements(mixed_project.elements, mixed_project.path)


def test_generate_elements_runs_every_source(mixed_elements) -> None:
    ids = [e.id for e in mixed_elements]
    assert len(ids) == len(set(ids))
    kinds = [e.type for e in mixed_elements]
    assert kinds.count("print_path") == 3 and kinds.count("task_point") == 2
    drill = next(e for e in mixed_elements if e.id == "drill-1")
    assert drill.attributes["action"] == "drill" and drill.attributes["params"] == {"depth": 0.05}
    assert np.allclose(drill.T_world_element[:3, 2], [0, 0, -1])
    mark = next(e for e in mixed_elements if e.id == "mark-1")
    assert mark.layer == 2 and mark.attributes["action"] == "mark"
    paths = [e for e in mixed_elements if e.type == "print_path"]
    assert [p.supports for p in paths] == [(), ("P000",), ("P001",)]
    block = next(e for e in mixed_elements if e.type == "block" and e.layer == 5)
    assert block.supports and all(s.startswith("B") for s in block.supports)


def test_elements_json_round_trip(mixed_elements) -> None:
    text = json.dumps(elements_to_json(mixed_elements))
    back = elements_from_json(json.loads(text))
    for a, b in zip(mixed_elements, back, strict=True):
        assert a.to_dict() == b.to_dict()
        assert isinstance(b, Element) and np.array_equal(a.T_world_element, b.T_world_element)


def test_duplicate_task_point_ids_are_rejected(tmp_path) -> None:
    text = """
name: dup
elements:
  - task_points:
      - {id: B0000, pose: {xyz: [0, 0, 0]}}
  - cabin: {}
"""
    project = parse_project(text, tmp_path / "p.yaml", tmp_path)
    with pytest.raises(InputError, match=r"elements\[0\]\.task_points\[0\]\.id"):
        generate_elements(project.elements, project.path)


def test_design_stage_writes_elements_and_site_plan(mixed_project, tmp_path) -> None:
    ctx = BuildContext(project=mixed_project, out=tmp_path)
    stage_design(ctx)
    ctx.finish()
    data = json.loads((tmp_path / "elements.json").read_text())
    assert data["count"] == len(ctx.elements) == len(data["elements"])
    for d in data["elements"][:: max(1, len(data["elements"]) // 50)]:
        assert {"id", "type", "T_world_element", "layer", "supports", "part"} <= d.keys()
        assert np.asarray(d["T_world_element"]).shape == (4, 4)
    doc = ezdxf.readfile(tmp_path / "site_plan.dxf")
    assert not doc.audit().has_errors
    rows = {item: value for stage, item, value in ctx.summary if stage == "design"}
    assert rows["blocks per part"].startswith("A ")
    assert rows["print path layers"] == "3"


def test_standing_elements_make_their_boxes_once_and_travel_without_them(mixed_elements) -> None:
    standing = Standing(mixed_elements)
    T, extents = element_boxes(standing)
    assert element_boxes(standing)[0] is T and not T.flags.writeable
    np.testing.assert_array_equal(T, element_boxes(list(mixed_elements))[0])
    np.testing.assert_array_equal(extents, element_boxes(list(mixed_elements))[1])
    copy = pickle.loads(pickle.dumps(standing))  # as a Dask worker receives a study
    assert isinstance(copy, Standing) and "boxes" not in vars(copy)
    assert [e.id for e in copy] == [e.id for e in mixed_elements]
    assert not element_boxes(copy)[0].flags.writeable


def test_element_meshes(mixed_elements) -> None:
    from fabflow.design.geometry import blocks_mesh, element_mesh

    blocks = [e for e in mixed_elements if e.type == "block"]
    mesh = blocks_mesh(blocks)
    assert mesh.is_watertight and len(mesh.faces) == 12 * len(blocks)
    assert mesh.volume == pytest.approx(sum(float(np.prod(e.extents)) for e in blocks))
    layer = next(e for e in mixed_elements if e.type == "print_path")
    ribbon = element_mesh(layer)
    a = layer.attributes
    assert ribbon.volume == pytest.approx(a["length"] * a["bead_width"] * a["layer_height"])
    assert ribbon.bounds[1, 2] == pytest.approx(layer.T_world_element[2, 3])
    assert len(element_mesh(next(e for e in mixed_elements if e.type == "task_point")).faces) == 0


@settings(deadline=None, max_examples=15)
@given(
    length=st.floats(2.0, 7.0),
    width=st.floats(2.0, 7.0),
    eave=st.floats(1.0, 3.5),
    roof=st.floats(0.0, 2.0),
    block_length=st.floats(0.4, 1.2),
    door=st.booleans(),
)
def test_any_cabin_stands_without_overlaps(length, width, eave, roof, block_length, door) -> None:
    openings = (
        [
            Opening(
                wall="front", kind="door", center=width / 2, width=0.8, height=min(2.0, eave - 0.3)
            )
        ]
        if door and eave > 1.0 and width > 1.4
        else []
    )
    spec = CabinSpec(
        length=length,
        width=width,
        eave_height=eave,
        height=eave + roof,
        block=BlockSize(length=block_length),
        openings=openings,
    )
    b = cabin_blocks(spec)
    sup = compute_supports(b.T_world_block, b.extents)
    assert all(len(sup[i]) > 0 for i in np.flatnonzero(b.layer > 0))
    assert max_overlap_volume(b.T_world_block, b.extents) <= 1e-6
    plain = b.kind == "block"
    assert np.all(b.extents[plain, 0] <= block_length + 1e-9)


def test_site_sensors_in_world_frame() -> None:

    from fabflow.localize.site import site_sensors
    from fabflow.project import load_project

    anchors, instrument = site_sensors(load_project(PROJECTS / "cabin"))
    assert np.allclose(anchors["A1"], [-0.4, -1.0, 1.0]) and instrument is None
    anchors, instrument = site_sensors(load_project(PROJECTS / "print_path"))
    assert anchors is None and np.allclose(instrument[:3, 3], [-2.5, -2.5, 1.6])


@settings(deadline=None, max_examples=30, derandomize=True)
@given(
    length=st.floats(2.0, 9.0),
    width=st.floats(2.0, 9.0),
    eave=st.floats(1.0, 3.5),
    roof=st.floats(0.0, 2.0),
    block_length=st.floats(0.4, 1.2),
    block_height=st.floats(0.05, 0.3),
    door=st.booleans(),
)
def test_block_bound_is_an_upper_bound(
    length, width, eave, roof, block_length, block_height, door
) -> None:
    openings = (
        [Opening(wall="front", kind="door", center=width / 2, width=0.8, height=eave * 0.5)]
        if door and width > 1.4
        else []
    )
    try:
        spec = CabinSpec(
            length=length,
            width=width,
            eave_height=eave,
            height=eave + roof,
            block=BlockSize(length=block_length, height=block_height),
            openings=openings,
        )
    except ValueError:
        return
    assert cabin_block_bound(spec) >= len(cabin_blocks(spec))


def test_block_bound_of_a_nanometre_block_is_quick() -> None:
    t0 = time.perf_counter()
    bound = cabin_block_bound(CabinSpec(block=BlockSize(height=1e-9)))
    assert bound > 1e9 and time.perf_counter() - t0 < 0.1


def test_many_openings_validate_fast() -> None:
    openings = [
        {"wall": "left", "center": 0.2 + 0.003 * i, "width": 1e-3, "height": 0.5}
        for i in range(1200)
    ]
    t0 = time.perf_counter()
    spec = CabinSpec(lintel_bearing=1e-4, openings=openings)
    assert len(spec.openings) == 1200 and time.perf_counter() - t0 < 1
    openings[700]["center"] = openings[699]["center"] + 1e-4
    with pytest.raises(ValueError, match=r"openings\[699\] and openings\[700\] overlap"):
        CabinSpec(lintel_bearing=1e-4, openings=openings)


def test_cabin_without_robot_parts_builds(tmp_path) -> None:
    from typer.testing import CliRunner

    from fabflow.cli import app

    text = (PROJECTS / "cabin" / "project.yaml").read_text()
    text = text.replace("origin: [0.0, 0.0, 0.0]", "origin: [0.0, 0.0, 0.0]\n      robot_parts: []")
    (tmp_path / "project.yaml").write_text(text)
    result = CliRunner().invoke(app, ["build", str(tmp_path), "-o", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert "nothing to plan" in (tmp_path / "out" / "plan.json").read_text()
