"""Point cloud filters (the files: test_pointcloud_io.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.positioning.pointcloud import (
    crop_box,
    crop_radius,
    estimate_normals,
    remove_statistical_outliers,
    voxel_downsample,
)


@pytest.fixture
def cloud() -> np.ndarray:
    return np.random.default_rng(1).uniform(-2, 2, (500, 3))


def test_voxel_downsample_centroids() -> None:
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.03, 0.03], [0.51, 0.0, 0.0]])
    out, _ = voxel_downsample(pts, 0.1)
    assert len(out) == 2
    assert np.any(np.all(np.isclose(out, [0.02, 0.02, 0.02]), axis=1))
    out2, _ = voxel_downsample(pts, 0.1, min_points=2)
    np.testing.assert_allclose(out2, [[0.02, 0.02, 0.02]])


@settings(deadline=None, max_examples=25)
@given(st.floats(0.05, 1.0), st.integers(0, 2**31 - 1))
def test_voxel_downsample_one_point_per_voxel(size: float, seed: int) -> None:
    pts = np.random.default_rng(seed).uniform(-3, 3, (300, 3))
    out, _ = voxel_downsample(pts, size)
    keys = np.floor((out - pts.min(axis=0)) / size)
    assert len(np.unique(keys, axis=0)) == len(out)
    assert len(out) <= len(pts)


def test_normals_of_a_plane_point_to_viewpoint() -> None:
    rng = np.random.default_rng(2)
    pts = np.c_[rng.uniform(0, 1, (400, 2)), np.zeros(400)]
    n, var = estimate_normals(pts, k=10, viewpoint=[0, 0, -5], return_planarity=True)
    np.testing.assert_allclose(n, np.tile([0, 0, -1.0], (400, 1)), atol=1e-9)
    assert var.max() < 1e-12


def test_crops_and_outliers(cloud: np.ndarray) -> None:
    inside = crop_radius(cloud, [0, 0, 0], 1.0)
    assert np.all(np.linalg.norm(inside, axis=1) <= 1.0)
    assert len(inside) == int(np.sum(np.linalg.norm(cloud, axis=1) <= 1.0))
    boxed = crop_box(cloud, [-1, -1, -1], [1, 1, 0])
    assert np.all(boxed[:, 2] <= 0) and len(boxed) > 0
    dirty = np.vstack([cloud, [[50.0, 50.0, 50.0]]])
    kept, mask = remove_statistical_outliers(dirty, k=10, std_ratio=2.0)
    assert not mask[-1] and mask[:-1].mean() > 0.9
    assert len(kept) == mask.sum()


def test_bad_arrays_rejected() -> None:
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        voxel_downsample(np.zeros((4, 2)), 0.1)
    with pytest.raises(InputError, match="positive"):
        voxel_downsample(np.zeros((4, 3)), 0.0)
