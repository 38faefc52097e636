"""Stones on rough terrain: rocks, ground, placement, swing scans and the vision map."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from fabflow.errors import InputError
from fabflow.sensors.lidar import VLP16
from fabflow.sensors.stone_scene import (
    CONCAVE_FILL,
    HEAP_LIDARS,
    SINK,
    Ground,
    StoneSite,
    cabin_swing_poses,
    rock_mesh,
    scan_site,
    stone_site,
    uneven_ground,
    vision_map,
)
from fabflow.transforms.se3 import apply_T, make_T
from fabflow.transforms.so3 import exp_so3


@functools.cache
def _site() -> StoneSite:
    return stone_site(np.random.default_rng(2))


def _swing(site: StoneSite) -> np.ndarray:
    base = make_T(np.eye(3), [0.0, 0.0, float(site.ground.height([[0.0, 0.0]])[0])])
    return cabin_swing_poses(base)


def test_vlp16_pattern() -> None:
    d = VLP16.directions()
    assert d.shape == (16 * 1800, 3)
    elev = np.degrees(np.arcsin(d[:, 2]))
    assert elev.min() == pytest.approx(-15.0) and elev.max() == pytest.approx(15.0)
    assert np.allclose(np.unique(np.round(elev, 9)), np.arange(-15.0, 15.5, 2.0))
    assert VLP16.max_range == 100.0 and VLP16.range_sigma == 0.03 and VLP16.rate_hz == 10.0


@pytest.mark.parametrize("convex", [True, False])
def test_rock_extents_centre_and_volume(convex: bool) -> None:
    extents = np.array([1.5, 1.1, 0.8])
    ellipsoid = np.pi / 6 * extents.prod()
    for seed in range(6):
        rock = rock_mesh(np.random.default_rng(seed), extents, convex)
        assert rock.is_watertight and rock.is_winding_consistent and rock.volume > 0
        np.testing.assert_allclose(rock.extents, extents, rtol=1e-9)
        np.testing.assert_allclose(rock.center_mass, 0.0, atol=1e-9)
        assert (150 if convex else 500) <= len(rock.faces) <= 3000
        fill = rock.volume / rock.convex_hull.volume
        if convex:
            assert rock.is_convex and fill == pytest.approx(1.0, abs=1e-9)
            assert rock.volume == pytest.approx(ellipsoid, rel=0.15)
        else:
            assert not rock.is_convex and fill < min(CONCAVE_FILL, 0.93) + 1e-12
            assert 0.7 * ellipsoid < rock.volume < 1.05 * ellipsoid


def test_rocks_differ_by_seed_and_repeat_with_it() -> None:
    a, b, c = (rock_mesh(np.random.default_rng(s), (1, 1, 1), False) for s in (1, 1, 2))
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert not np.allclose(a.vertices, c.vertices)
    with pytest.raises(InputError):
        rock_mesh(np.random.default_rng(0), (1.0, -1.0, 1.0), True)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    shape=st.tuples(st.integers(2, 6), st.integers(2, 6)),
    spacing=st.floats(0.05, 3.0),
    where=st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0)),
)
def test_ground_height_is_bilinear_between_nodes(
    seed: int, shape: tuple[int, int], spacing: float, where: tuple[float, float]
) -> None:
    rng = np.random.default_rng(seed)
    ground = Ground(-3.0, 7.5, spacing, rng.normal(0.0, 0.5, shape))
    i, j = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    nodes = np.c_[-3.0 + i.ravel() * spacing, 7.5 + j.ravel() * spacing]
    np.testing.assert_allclose(ground.height(nodes), ground.heights.ravel(), atol=1e-12)
    f = np.array(where) * (np.array(shape) - 1)
    ci, cj = np.minimum(np.floor(f).astype(int), np.array(shape) - 2)
    corners = ground.heights[ci : ci + 2, cj : cj + 2]
    h = ground.height([[-3.0 + f[0] * spacing, 7.5 + f[1] * spacing]])[0]
    assert corners.min() - 1e-12 <= h <= corners.max() + 1e-12


def test_ground_mesh_and_uneven_ground() -> None:
    ground = uneven_ground(np.random.default_rng(0), (-6.0, -10.0), (14.0, 10.0))
    assert ground.heights.shape == (81, 81)
    np.testing.assert_allclose(ground.bounds, [[-6.0, -10.0], [14.0, 10.0]])
    assert np.sqrt(np.mean(ground.heights**2)) == pytest.approx(0.08, rel=0.35)
    mesh = ground.mesh()
    assert len(mesh.faces) == 2 * 80 * 80 and np.all(mesh.face_normals[:, 2] > 0)
    np.testing.assert_allclose(mesh.vertices[:, 2], ground.height(mesh.vertices[:, :2]))
    # inside the cells the triangles stay within a centimetre of the bilinear surface
    centres = mesh.triangles_center
    assert np.max(np.abs(centres[:, 2] - ground.height(centres[:, :2]))) < 0.01
    with pytest.raises(InputError):
        Ground(0.0, 0.0, 0.25, np.zeros((1, 4)))


def test_stones_are_apart_resting_and_sized() -> None:
    site = _site()
    assert site.n_stones == 7 and site.T_world_stone.shape == (7, 4, 4)
    volumes = np.array([m.volume for m in site.models])
    assert np.all((volumes > 0.5 * 0.85) & (volumes < 1.0 * 1.15))
    assert sum(m.is_convex for m in site.models) == 4
    meshes = [site.stone_mesh(i) for i in range(7)]
    for i, mesh in enumerate(meshes):
        np.testing.assert_allclose(mesh.center_mass, site.centers_of_mass()[i], atol=1e-9)
        lowest = np.min(mesh.vertices[:, 2] - site.ground.height(mesh.vertices[:, :2]))
        assert lowest == pytest.approx(-SINK, abs=1e-9)  # touching, then sunk 2 cm
        xy = mesh.vertices[:, :2]
        assert np.all((xy >= [2.5, -4.0]) & (xy <= [9.5, 4.0]))
        others = np.concatenate([m.vertices[:, :2] for k, m in enumerate(meshes) if k != i])
        assert cKDTree(others).query(xy)[0].min() >= 0.4 - 1e-9


def test_stones_that_cannot_fit_raise() -> None:
    with pytest.raises(InputError, match="cannot place 7 stones"):
        stone_site(np.random.default_rng(0), region_min=(3.0, -2.0), region_max=(7.0, 2.0))
    with pytest.raises(InputError, match="not within the ground"):
        ground = uneven_ground(np.random.default_rng(0), (0.0, 0.0), (5.0, 5.0))
        stone_site(np.random.default_rng(0), ground=ground)


def test_scene_owners_exclude_and_moved() -> None:
    site = _site()
    scene, owner = site.scene(), site.face_owner()
    np.testing.assert_array_equal(scene.face_attributes["owner"], owner)
    for i in range(site.n_stones):
        faces = scene.triangles[owner == i]
        np.testing.assert_allclose(faces, site.stone_mesh(i).triangles)
    partial = site.scene(exclude=[2])
    assert len(partial.faces) == len(scene.faces) - len(site.models[2].faces)
    assert 2 not in site.face_owner(exclude=[2])
    T_new = make_T(exp_so3([0.0, 0.0, 1.0]), [-3.0, 5.0, 0.4])
    moved = site.moved(2, T_new)
    np.testing.assert_array_equal(moved.T_world_stone[2], T_new)
    keep = np.arange(7) != 2
    np.testing.assert_array_equal(moved.T_world_stone[keep], site.T_world_stone[keep])
    assert not np.allclose(site.T_world_stone[2], T_new)  # the original is untouched
    np.testing.assert_allclose(moved.stone_mesh(2).center_mass, [-3.0, 5.0, 0.4], atol=1e-9)
    with pytest.raises(InputError):
        site.moved(7, T_new)
    with pytest.raises(InputError):
        site.moved(0, np.diag([2.0, 1.0, 1.0, 1.0]))


def test_swing_poses_put_the_lidars_on_the_cabin_roof() -> None:
    base = make_T(exp_so3([0.0, 0.0, 0.4]), [1.0, 2.0, 0.1])
    poses = cabin_swing_poses(base, [-90.0, 0.0, 45.0])
    assert poses.shape == (6, 4, 4)
    np.testing.assert_allclose(poses[2], base @ HEAP_LIDARS[0])
    local = apply_T(np.linalg.inv(base), poses[:, :3, 3])
    np.testing.assert_allclose(np.hypot(local[:, 0], local[:, 1]), np.hypot(1.0, 0.6))
    np.testing.assert_allclose(local[:, 2], 2.8)
    heading = np.radians([-90.0, 0.0, 45.0]) + 0.4
    forward = np.c_[np.cos(heading), np.sin(heading), np.zeros(3)]
    # horizontal LiDAR: spin axis tilted 25 deg forward; vertical: along the cabin's x
    np.testing.assert_allclose(np.sum(poses[0::2, :3, 2] * forward, 1), np.sin(np.radians(25)))
    np.testing.assert_allclose(np.sum(poses[1::2, :3, 2] * forward, 1), np.cos(np.radians(25)))


def test_scan_returns_lie_on_their_owner() -> None:
    site = _site()
    poses = _swing(site)
    exact = scan_site(
        site, poses, np.random.default_rng(1), dataclasses.replace(VLP16, range_sigma=0.0)
    )
    assert len(poses) == 16 and len(exact) > 50_000
    counts = np.bincount(exact.owner + 1, minlength=8)
    assert np.all(counts[1:] > 300)  # the swing sees every stone
    for lidar in range(2):  # and both LiDARs contribute to them
        assert np.sum((exact.owner >= 0) & (exact.lidar_index % 2 == lidar)) > 2000
    rng = np.random.default_rng(0)
    for i in range(-1, 7):
        mesh = site.ground.mesh() if i < 0 else site.stone_mesh(i)
        own = exact.points_world[exact.owner == i]
        pick = own[rng.choice(len(own), min(len(own), 300), replace=False)]
        assert trimesh.proximity.closest_point(mesh, pick)[1].max() < 1e-4
    ranges = np.linalg.norm(exact.points_world - poses[exact.lidar_index, :3, 3], axis=1)
    assert ranges.max() <= VLP16.max_range
    noisy = scan_site(site, poses, np.random.default_rng(1))
    np.testing.assert_array_equal(noisy.face_index, exact.face_index)
    gap = np.linalg.norm(noisy.points_world - exact.points_world, axis=1)
    assert np.std(gap) < 0.03 and np.quantile(gap, 0.999) < 4 * 0.03
    with pytest.raises(InputError):
        scan_site(site, poses, rng, sensor_of_pose=[0, 1])


def test_vision_map_sees_from_above_only() -> None:
    site = _site()
    pts = vision_map(site, np.random.default_rng(3), spacing=0.05, sigma=0.0)
    scene = site.scene()
    _, distance, face = trimesh.proximity.closest_point(scene, pts[::7])
    assert distance.max() < 1e-6
    assert np.all(scene.face_normals[face, 2] > -0.1)
    # the stones have undersides, which the drone misses; it sees every stone's top
    assert np.any(scene.face_normals[site.face_owner() >= 0, 2] < -0.5)
    owner = site.face_owner()[face]
    assert set(np.unique(owner)) == set(range(-1, 7))
    lo = np.min([site.stone_mesh(i).vertices[:, :2].min(0) for i in range(7)], axis=0) - 1.5
    hi = np.max([site.stone_mesh(i).vertices[:, :2].max(0) for i in range(7)], axis=0) + 1.5
    assert np.all((pts[:, :2] > lo - 0.3) & (pts[:, :2] < hi + 0.3))
    assert len(pts) == pytest.approx(np.prod(hi - lo) / 0.05**2, rel=0.25)


def test_vision_map_noise_and_source_frame() -> None:
    site = _site()
    T = make_T(exp_so3([0.02, -0.01, 2.0]), [100.0, -40.0, 3.0])
    world = vision_map(site, np.random.default_rng(4), spacing=0.08)
    source = vision_map(site, np.random.default_rng(4), spacing=0.08, T_source_world=T)
    np.testing.assert_allclose(source, apply_T(T, world), atol=1e-9)
    exact = vision_map(site, np.random.default_rng(4), spacing=0.08, sigma=0.0)
    noise = world - exact
    assert np.std(noise) == pytest.approx(0.01, rel=0.1)
