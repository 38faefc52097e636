"""Print paths: Hermite sampling accuracy and speed, tool frames, layers, mesh slicing."""

from __future__ import annotations

import time

import ezdxf
import numpy as np
import pytest
import shapely
import trimesh
from helpers import PROJECTS
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.design.dxf_in import read_dxf_contours
from fabflow.design.generate import generate_elements
from fabflow.design.hermite import sample_hermite
from fabflow.design.print_path import (
    element_tool_frames,
    order_contours,
    print_path_elements,
    sample_print_path,
    slice_mesh,
    tool_frames,
)
from fabflow.design.specs import PrintPathSpec
from fabflow.errors import FabflowError, InputError
from fabflow.project import parse_project
from fabflow.schema import Limits, PoseSpec
from fabflow.tasks.planner import make_plan

SINE_WALL = PROJECTS / "print_path" / "sine_wall.dxf"
MAX_DEVIATION = 5e-4  # metres: the bound on the sampled path vs the drawing


def _distance_to(polyline: np.ndarray, points: np.ndarray) -> np.ndarray:
    return shapely.distance(shapely.LineString(polyline[:, :2]), shapely.points(points[:, :2]))


def test_circle_is_sampled_within_tolerance_at_constant_speed() -> None:
    th = np.linspace(0, 2 * np.pi, 181)
    pts = np.column_stack([np.cos(th), np.sin(th), np.zeros_like(th)])
    s = sample_hermite(pts, speed=0.1, rate_hz=100.0)
    r = np.linalg.norm(s.points[:, :2], axis=1)
    assert np.abs(r - 1.0).max() < MAX_DEVIATION
    steps = np.linalg.norm(np.diff(s.points, axis=0), axis=1)
    assert np.allclose(steps[:-1], 0.001, rtol=1e-3)
    assert steps[-1] <= 0.001 + 1e-9
    assert np.allclose(np.diff(s.t), 0.01)
    assert s.length == pytest.approx(2 * np.pi, rel=1e-4)


def test_sharp_corners_stay_within_tolerance() -> None:
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 0]], dtype=float)
    s = sample_hermite(square, speed=0.2, rate_hz=100.0)
    dev = _distance_to(square, s.points)
    assert dev.max() < MAX_DEVIATION
    assert s.max_deviation >= dev.max() - 1e-12
    assert np.all(np.abs(np.linalg.norm(s.tangents, axis=1) - 1) < 1e-9)
    # the tangent turns continuously through the corners: sampled finely, no jumps
    fine = sample_hermite(square, speed=0.2, rate_hz=20000.0)
    turn = np.arccos(np.clip(np.sum(fine.tangents[1:] * fine.tangents[:-1], axis=1), -1, 1))
    assert turn.max() < 0.1
    # ... and monotonically (corner fillets, no S-bends): total turning = 3 x 90 degrees
    assert np.sum(turn) == pytest.approx(1.5 * np.pi, rel=1e-3)


@settings(deadline=None, max_examples=30)
@given(
    st.lists(
        st.tuples(st.floats(-1, 1), st.floats(-1, 1)), min_size=2, max_size=7, unique=True
    ).filter(lambda p: np.linalg.norm(np.diff(np.array(p), axis=0), axis=1).min() > 0.02),
    st.floats(0.05, 0.5),
)
def test_hermite_property_deviation_and_speed(xy, speed) -> None:
    pts = np.column_stack([np.array(xy), np.zeros(len(xy))])
    s = sample_hermite(pts, speed=speed, rate_hz=100.0)
    assert _distance_to(pts, s.points).max() < MAX_DEVIATION
    assert np.allclose(s.points[0], pts[0]) and np.allclose(s.points[-1], pts[-1], atol=1e-9)
    # constant speed: arc length between samples is speed / rate (chords may be shorter at
    # tight bends, never longer)
    steps = np.linalg.norm(np.diff(s.points, axis=0), axis=1)
    assert steps.max() <= speed / 100.0 * (1 + 1e-2)
    assert np.median(steps[:-1]) == pytest.approx(speed / 100.0, rel=1e-3)
    # fillets cut the corners by well under a millimetre each
    drawn = np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()
    assert s.length == pytest.approx(drawn, abs=1e-3 * len(pts))


def test_tool_frames_point_down_and_along_the_path() -> None:
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0.5]], dtype=float)
    tangents = np.array([[1, 0, 0], [1, 1, 0], [0, 1, 1]], dtype=float)
    T = tool_frames(pts, tangents)
    R = T[:, :3, :3]
    assert np.allclose(R.transpose(0, 2, 1) @ R, np.eye(3))
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(R[:, :, 2], [0, 0, -1])
    x_expected = tangents * [1, 1, 0]
    x_expected /= np.linalg.norm(x_expected, axis=1)[:, None]
    assert np.allclose(R[:, :, 0], x_expected)
    assert np.allclose(T[:, :3, 3], pts)


@pytest.fixture(scope="module")
def wall_elements():
    spec = PrintPathSpec(
        dxf=SINE_WALL,
        layers=["WALL_OUTER"],
        n_layers=4,
        layer_height=0.02,
        origin=PoseSpec(xyz=(1.0, 2.0, 0.0), abc_deg=(30.0, 0.0, 0.0)),
    )
    return print_path_elements(spec)


def test_sine_wall_layers(wall_elements) -> None:
    assert [e.id for e in wall_elements] == ["P000", "P001", "P002", "P003"]
    assert [e.layer for e in wall_elements] == [0, 1, 2, 3]
    z = [e.T_world_element[2, 3] for e in wall_elements]
    assert np.allclose(z, [0.02, 0.04, 0.06, 0.08])
    e = wall_elements[0]
    assert e.attributes["closed"] and all(e.attributes["extrude"])
    assert np.allclose(e.polyline[0], e.polyline[-1])
    # the outline of a 4 m wall, 300 mm thick with half-round ends: ~2 x 4.4 m + 2 x 0.47 m
    assert 9.0 < e.attributes["length"] < 10.5
    assert e.attributes["dxf_layers"] == ["WALL_OUTER"]


def test_sine_wall_sampling_stays_on_the_drawing(wall_elements) -> None:
    e = wall_elements[1]
    sampled, T_world_tool = sample_print_path(e)
    fine = read_dxf_contours(SINE_WALL, ["WALL_OUTER"], flatten_tol=1e-5)[0]
    dev = _distance_to(fine.points, sampled.points)
    assert dev.max() < MAX_DEVIATION
    steps = np.linalg.norm(np.diff(sampled.points, axis=0), axis=1)
    assert np.allclose(steps[:-1], 0.001, rtol=2e-3)
    assert np.allclose(T_world_tool[:, :3, 2], [0, 0, -1])
    local = np.column_stack([sampled.points, np.ones(len(sampled.points))]) @ e.T_world_element.T
    assert np.allclose(T_world_tool[:, :3, 3], local[:, :3])
    frames = element_tool_frames(e)
    assert frames.shape == (len(e.polyline), 4, 4)


def test_contours_joined_by_travel_moves() -> None:
    a = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 0]], dtype=float)
    b = a + np.array([3.0, 0.0, 0.0])
    line = np.array([[10, 0, 0], [8, 0, 0]], dtype=float)
    path = order_contours([b, line, a], [True, False, True], start=np.array([1.2, 1.2, 0]))
    # nearest first: a, starting at its corner (1, 1); then b at (3, 1); then the line
    assert np.allclose(path.points[0], [1, 1, 0])
    assert path.extrude.tolist().count(False) == 2
    assert np.allclose(path.points[-2:], [[8, 0, 0], [10, 0, 0]])
    s = sample_hermite(path.points, 0.1, 100.0, path.extrude)
    assert (~s.extrude).any() and s.extrude[0] and s.extrude[-1]


def test_mesh_slicing_gives_analytic_contours() -> None:
    box = trimesh.creation.box([0.8, 0.4, 0.1])
    layers = slice_mesh(box, 0.02)
    assert len(layers) == 5
    for _, (ring,) in layers:
        assert len(ring) == 5  # four corners and the repeated first
        assert shapely.Polygon(ring[:, :2]).area == pytest.approx(0.32)
    assert [z for z, _ in layers] == pytest.approx([-0.04, -0.02, 0.0, 0.02, 0.04])

    n = 64
    annulus = trimesh.creation.annulus(r_min=0.3, r_max=0.5, height=0.1, sections=n)
    (_, rings), *_ = slice_mesh(annulus, 0.05)
    assert len(rings) == 2
    polygon_area = sorted(0.5 * n * r * r * np.sin(2 * np.pi / n) for r in (0.3, 0.5))
    areas = sorted(shapely.Polygon(r[:, :2]).area for r in rings)
    assert areas == pytest.approx(polygon_area, rel=1e-9)
    for ring in rings:
        radius = np.linalg.norm(ring[:, :2], axis=1)
        assert np.ptp(radius) < 1e-9  # every vertex on a cylinder edge


def test_print_path_from_mesh(tmp_path) -> None:
    cyl = trimesh.creation.cylinder(radius=0.4, height=0.1, sections=48)
    cyl.apply_translation([0, 0, 0.05])
    path = tmp_path / "column.stl"
    cyl.export(path)
    elements = print_path_elements(PrintPathSpec(mesh=path, layer_height=0.025))
    assert len(elements) == 4
    assert np.allclose([e.T_world_element[2, 3] for e in elements], [0.025, 0.05, 0.075, 0.1])
    for e in elements:
        assert np.allclose(np.linalg.norm(e.polyline[:, :2], axis=1).max(), 0.4)
        assert np.allclose(e.polyline[:, 2], 0.0)
    capped = print_path_elements(PrintPathSpec(mesh=path, layer_height=0.025, n_layers=2))
    assert len(capped) == 2


def test_bad_mesh(tmp_path) -> None:
    path = tmp_path / "open.stl"
    trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 1]], faces=[[0, 1, 2]]).export(path)
    with pytest.raises(InputError, match="watertight"):
        print_path_elements(PrintPathSpec(mesh=path))


def test_open_path_allowed_when_not_closed(tmp_path) -> None:
    doc = ezdxf.new(units=4)
    doc.modelspace().add_lwpolyline([(0, 0), (1000, 0), (1000, 500)], dxfattribs={"layer": "P"})
    path = tmp_path / "open.dxf"
    doc.saveas(path)
    with pytest.raises(InputError, match="open contour"):
        print_path_elements(PrintPathSpec(dxf=path))
    (e,) = print_path_elements(PrintPathSpec(dxf=path, closed=False, n_layers=1))
    assert not e.attributes["closed"] and e.attributes["length"] == pytest.approx(1.5)


def test_tool_frames_survive_repeated_waypoints() -> None:
    from fabflow.design.elements import Element

    poly = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 1, 0]], dtype=float)
    e = Element(id="P", type="print_path", T_world_element=np.eye(4), polyline=poly)
    T = element_tool_frames(e)
    assert np.isfinite(T).all()
    assert np.allclose(T[0, :3, 0], [1, 0, 0]) and np.allclose(T[-1, :3, 0], [0, 1, 0])
    sampled, _ = sample_print_path(e)
    assert _distance_to(poly, sampled.points).max() < MAX_DEVIATION


def _column(tmp_path, height: float = 0.1) -> object:
    cyl = trimesh.creation.cylinder(radius=0.4, height=height, sections=48)
    cyl.apply_translation([0, 0, height / 2])
    path = tmp_path / "column.stl"
    cyl.export(path)
    return path


def test_mesh_slices_and_path_samples_are_bounded_by_the_limits(tmp_path) -> None:
    path = _column(tmp_path)
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=r"makes 10000000 layers.*limits\.max_elements"):
        print_path_elements(PrintPathSpec(mesh=path, layer_height=1e-8))
    with pytest.raises(InputError, match="lower than one layer"):
        print_path_elements(PrintPathSpec(mesh=path, layer_height=1.0))
    with pytest.raises(InputError, match=r"limits\.max_path_samples"):
        print_path_elements(PrintPathSpec(dxf=SINE_WALL, layers=["WALL_OUTER"], speed=1e-9))
    few = Limits(max_path_samples=1000)
    with pytest.raises(InputError, match=r"more than limits\.max_path_samples = 1000"):
        print_path_elements(PrintPathSpec(dxf=SINE_WALL, layers=["WALL_OUTER"]), limits=few)
    assert time.perf_counter() - t0 < 5
    assert len(print_path_elements(PrintPathSpec(mesh=path, layer_height=0.025))) == 4


def test_tall_layers_are_refused_by_the_planner_not_a_crash() -> None:
    project = parse_project(
        (PROJECTS / "print_path" / "project.yaml")
        .read_text()
        .replace("layer_height: 0.02", "layer_height: 100"),
        base_dir=PROJECTS / "print_path",
    )
    elements = generate_elements(project.elements, project.path, project.limits)
    with pytest.raises(FabflowError, match="outside what the arm reaches"):
        make_plan(project, elements)
