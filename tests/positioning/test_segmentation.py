"""Map segmentation and segment-based global registration."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import LocalizationError
from fabflow.positioning.global_registration import (
    REGISTRATION_SEGMENTATION,
    fpfh,
    register_maps,
)
from fabflow.positioning.pointcloud import estimate_normals
from fabflow.positioning.segmentation import (
    SegmentationParams,
    euclidean_clusters,
    ransac_plane,
    segment_map,
)
from fabflow.sensors.site_scene import SiteLandmarks, site_scene
from fabflow.transforms.se3 import apply_T, inv_T, make_T, pose_error
from fabflow.transforms.so3 import exp_so3


def sample(mesh: trimesh.Trimesh, n: int, seed: int, noise: float = 0.005) -> np.ndarray:
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts) + np.random.default_rng(seed).normal(0, noise, (n, 3))


def yard() -> trimesh.Trimesh:
    """Ground with two boxes, a barrel and a flat slab (planar, to be discarded)."""
    at = make_T
    eye = np.eye(3)
    parts = [
        trimesh.creation.box(bounds=[[-6, -6, -0.02], [6, 6, 0.0]]),
        trimesh.creation.box(extents=(1.2, 0.8, 0.8), transform=at(eye, [2, 1, 0.4])),
        trimesh.creation.box(extents=(1.0, 1.0, 1.5), transform=at(eye, [-2, 2, 0.75])),
        trimesh.creation.cylinder(radius=0.3, height=0.9, transform=at(eye, [0, -3, 0.45])),
        trimesh.creation.box(extents=(2.0, 2.0, 0.02), transform=at(eye, [3, -3, 0.5])),
    ]
    return trimesh.util.concatenate(parts)


def test_ransac_plane_finds_the_tilted_ground() -> None:
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, (3000, 2))
    ground = np.c_[xy, 0.1 * xy[:, 0] + 0.3]
    clutter = rng.uniform([-5, -5, 1], [5, 5, 3], (500, 3))
    plane, inl = ransac_plane(np.vstack([ground, clutter]), 0.02, rng, max_tilt_deg=20)
    expected = np.array([-0.1, 0.0, 1.0]) / np.linalg.norm([-0.1, 0.0, 1.0])
    np.testing.assert_allclose(plane[:3], expected, atol=1e-6)
    assert inl[:3000].all() and not inl[3000:].any()
    # only near-vertical candidates allowed: no plane
    wall = np.c_[np.zeros(200), rng.uniform(0, 1, (200, 2))]
    plane, inl = ransac_plane(wall, 0.01, rng, max_tilt_deg=10)
    assert not inl.any()


def test_euclidean_clusters_by_gap() -> None:
    a = np.c_[np.linspace(0, 1, 21), np.zeros(21), np.zeros(21)]
    b = a + np.array([3.0, 0.0, 0.0])
    c = np.array([[10.0, 0.0, 0.0]])
    labels = euclidean_clusters(np.vstack([a, b, c]), 0.06, min_points=2)
    assert len(set(labels[:21])) == 1 and len(set(labels[21:42])) == 1
    assert labels[0] != labels[21] and labels[-1] == -1


def test_segment_map_finds_the_objects_and_drops_planar_ones() -> None:
    pts = sample(yard(), 60000, 1)
    seg = segment_map(pts, np.random.default_rng(2), SegmentationParams(cluster_distance=0.2))
    centroids = seg.centroids
    assert len(seg.segments) == 3 and seg.n_planar == 1
    for expected in ([2, 1, 0.4], [-2, 2, 0.75], [0, -3, 0.45]):
        assert np.min(np.linalg.norm(centroids - expected, axis=1)) < 0.15
    assert seg.ground_plane[2] > 0.99 and abs(seg.ground_plane[3]) < 0.02
    table = seg.object_table()
    assert {"id", "n_points", "centroid", "lower", "upper"} <= set(table[0])
    assert np.all(seg.labels[seg.ground] == -1)


@settings(deadline=None, max_examples=4)
@given(st.floats(-np.pi, np.pi), st.lists(st.floats(-20, 20), min_size=3, max_size=3))
def test_fpfh_is_invariant_to_rigid_motion(yaw: float, t: list[float]) -> None:
    # noisy points: exactly planar samples put many pair features on histogram bin edges
    pts = sample(yard(), 1500, 3, noise=0.003)
    nrm = estimate_normals(pts, k=15)
    T = make_T(exp_so3([0.1, -0.2, yaw]), t)
    a = fpfh(pts, nrm, 0.5, k=30)
    b = fpfh(apply_T(T, pts), nrm @ T[:3, :3].T, 0.5, k=30)
    same = np.all(np.abs(a - b) < 1e-6, axis=1)
    assert same.mean() > 0.995
    assert a.shape == (1500, 33)
    with_n = a[a.sum(axis=1) > 0]
    np.testing.assert_allclose(with_n.reshape(-1, 3, 11).sum(axis=2), 200.0, atol=1e-6)


@pytest.fixture(scope="module")
def site_maps() -> tuple[np.ndarray, np.ndarray]:
    """A 'LiDAR' map and a 'drone' map of the same small site."""
    scene = site_scene(landmarks=SiteLandmarks(ground_half_size=14.0))
    return sample(scene, 60000, 4, 0.01), sample(scene, 60000, 5, 0.01)


def test_global_registration_recovers_an_unknown_pose(
    site_maps: tuple[np.ndarray, np.ndarray],
) -> None:
    target, drone = site_maps
    T_src_world = make_T(exp_so3([0.0, 0.0, 2.2]), [30.0, -12.0, 3.0])
    res = register_maps(apply_T(T_src_world, drone), target, np.random.default_rng(6))
    err = pose_error(res.T_target_source, inv_T(T_src_world))
    assert np.linalg.norm(err[:3]) < 0.05 and np.degrees(np.linalg.norm(err[3:])) < 0.5
    assert res.rmse < 0.03 and res.n_centroid_matches >= 2
    assert res.matches.shape[1] == 2
    assert len(res.source.segments) >= 3


def test_global_registration_fails_loudly_on_unrelated_maps(
    site_maps: tuple[np.ndarray, np.ndarray],
) -> None:
    target, _ = site_maps
    other = sample(yard(), 40000, 7, 0.01)
    with pytest.raises(LocalizationError):
        register_maps(
            other, target, np.random.default_rng(8), segmentation=REGISTRATION_SEGMENTATION
        )
