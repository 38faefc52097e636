"""LiDAR simulator and site scene."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fabflow.design.elements import Element
from fabflow.errors import InputError
from fabflow.sensors.lidar import HESAI_QT64, LidarModel, simulate_scan
from fabflow.sensors.site_scene import SiteLandmarks, boxes_mesh, prism_mesh, site_scene
from fabflow.transforms.se3 import apply_T, make_T
from fabflow.transforms.so3 import exp_so3

SMALL = LidarModel(n_beams=16, horizontal_resolution_deg=2.0)


def test_hesai_pattern() -> None:
    d = HESAI_QT64.directions()
    assert d.shape == (64 * 600, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    elev = np.degrees(np.arcsin(d[:, 2]))
    assert elev.min() == pytest.approx(-52.1) and elev.max() == pytest.approx(52.1)
    assert HESAI_QT64.max_range == 20.0 and HESAI_QT64.range_sigma == 0.01
    assert HESAI_QT64.rate_hz == 10.0


def test_bad_model() -> None:
    with pytest.raises(InputError):
        LidarModel(n_beams=0)
    with pytest.raises(InputError):
        LidarModel(max_range=0.1, min_range=0.3)


def test_points_lie_on_the_room_walls_with_the_stated_noise() -> None:
    room = trimesh.creation.box(extents=(10.0, 8.0, 4.0))
    T = make_T(exp_so3([0.05, -0.02, 0.7]), [1.0, -0.5, 0.3])
    scan = simulate_scan(room, T, np.random.default_rng(0), SMALL)
    assert len(scan) == SMALL.n_beams * SMALL.n_columns  # a closed room: every ray returns
    exact_model = LidarModel(n_beams=16, horizontal_resolution_deg=2.0, range_sigma=0.0)
    exact = simulate_scan(room, T, np.random.default_rng(0), exact_model)
    world = apply_T(T, exact.points)
    gap = np.min(np.abs(np.abs(world) - [5.0, 4.0, 2.0]), axis=1)
    assert gap.max() < 1e-9
    np.testing.assert_array_equal(scan.ray_index, exact.ray_index)
    assert np.std(scan.ranges - exact.ranges) == pytest.approx(0.01, rel=0.1)
    np.testing.assert_allclose(np.linalg.norm(scan.points, axis=1), scan.ranges)


def test_range_limits_and_determinism() -> None:
    scene = site_scene()
    T = make_T(np.eye(3), [2.0, -2.0, 1.8])
    a = simulate_scan(scene, T, np.random.default_rng(5), SMALL)
    b = simulate_scan(scene, T, np.random.default_rng(5), SMALL)
    np.testing.assert_array_equal(a.points, b.points)
    assert a.ranges.max() <= SMALL.max_range + 0.05
    assert a.ranges.min() >= SMALL.min_range - 0.05
    # upward beams see the sky: fewer returns than rays
    assert len(a) < SMALL.n_beams * SMALL.n_columns


def test_site_scene_holds_landmarks_and_blocks() -> None:
    empty = site_scene()
    lo, hi = empty.bounds
    assert lo[2] == pytest.approx(0.0) and hi[2] > 5.0  # ground and the bridge railing
    block = Element(
        id="B0",
        type="block",
        T_world_element=make_T(exp_so3([0, 0, 0.3]), [1.0, 1.0, 0.0525]),
        extents=np.array([0.6, 0.105, 0.105]),
    )
    path = Element(id="P0", type="print_path", T_world_element=np.eye(4))
    scene = site_scene(built=[block, path], obstacles=[((5, 5, 0), (6, 6, 1))])
    assert len(scene.faces) == len(empty.faces) + 2 * 12
    only = site_scene(built=[block], landmarks=None)
    assert only.volume == pytest.approx(0.6 * 0.105 * 0.105)
    moved = site_scene(landmarks=SiteLandmarks(offset=(10.0, 0.0)))
    np.testing.assert_allclose(moved.bounds[:, 0], empty.bounds[:, 0] + 10.0)


def test_boxes_mesh_matches_trimesh_boxes() -> None:
    rng = np.random.default_rng(1)
    T = np.stack([make_T(exp_so3(rng.normal(size=3)), rng.normal(size=3)) for _ in range(5)])
    ext = rng.uniform(0.1, 1.0, (5, 3))
    mesh = boxes_mesh(T, ext)
    ref = trimesh.util.concatenate(
        [trimesh.creation.box(extents=e, transform=t) for t, e in zip(T, ext, strict=True)]
    )
    np.testing.assert_allclose(mesh.vertices, ref.vertices, atol=1e-12)
    assert mesh.volume == pytest.approx(float(np.prod(ext, axis=1).sum()))


def test_scan_sees_a_built_block() -> None:
    block = Element(
        id="B0",
        type="block",
        T_world_element=make_T(np.eye(3), [3.0, 0.0, 1.0]),
        extents=np.array([0.6, 0.6, 2.0]),
    )
    T = make_T(np.eye(3), [0.0, 0.0, 1.0])
    rng = np.random.default_rng(2)
    without = simulate_scan(site_scene(), T, rng, SMALL)
    with_block = simulate_scan(site_scene(built=[block]), T, rng, SMALL)
    near = np.abs(apply_T(T, with_block.points)[:, 0] - 2.7) < 0.05
    assert near.sum() > 3
    assert (np.abs(apply_T(T, without.points)[:, 0] - 2.7) < 0.05).sum() < near.sum()


def test_prism_mesh_of_a_non_convex_polygon() -> None:
    l_shape = [(0, 0), (2, 0), (2, 1), (1, 1), (1, 2), (0, 2)]
    mesh = prism_mesh(l_shape, 0.5, 3.5)
    assert abs(mesh.volume) == pytest.approx(3.0 * 3.0)
    np.testing.assert_allclose(mesh.bounds, [[0, 0, 0.5], [2, 2, 3.5]])
    # a ray through the notch of the L passes
    hits = mesh.ray.intersects_any([[1.5, 1.5, 10.0]], [[0.0, 0.0, -1.0]])
    assert not hits[0]
    scene = site_scene(prisms=[(l_shape, 0.5, 3.5)])
    assert len(scene.faces) == len(site_scene().faces) + len(mesh.faces)
