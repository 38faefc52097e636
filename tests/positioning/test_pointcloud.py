"""Point cloud I/O and filters."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.positioning.pointcloud import (
    crop_box,
    crop_radius,
    estimate_normals,
    read_point_cloud,
    remove_statistical_outliers,
    voxel_downsample,
    write_point_cloud,
)


@pytest.fixture
def cloud() -> np.ndarray:
    return np.random.default_rng(1).uniform(-2, 2, (500, 3))


@pytest.mark.parametrize(
    "name,binary", [("c.ply", True), ("c.ply", False), ("c.xyz", True), ("c.csv", True)]
)
def test_write_read_round_trip(tmp_path: Path, cloud: np.ndarray, name: str, binary: bool) -> None:
    normals = np.tile([0.0, 0.0, 1.0], (len(cloud), 1))
    write_point_cloud(tmp_path / name, cloud, normals if name.endswith("ply") else None, binary)
    back = read_point_cloud(tmp_path / name)
    np.testing.assert_allclose(back.points, cloud, atol=1e-7)
    if name.endswith("ply"):
        assert back.normals is not None
        np.testing.assert_allclose(back.normals, normals)


def test_read_binary_big_endian_float_ply_with_extra_properties_and_faces(tmp_path: Path) -> None:
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=">f4")
    inten = np.array([5, 6, 7, 8], dtype=">u2")
    rec = np.empty(4, dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("intensity", ">u2")])
    rec["x"], rec["y"], rec["z"], rec["intensity"] = pts[:, 0], pts[:, 1], pts[:, 2], inten
    header = (
        b"ply\nformat binary_big_endian 1.0\nelement vertex 4\nproperty float x\n"
        b"property float y\nproperty float z\nproperty ushort intensity\n"
        b"element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    )
    face = np.array([3], dtype="u1").tobytes() + np.array([0, 1, 2], dtype=">i4").tobytes()
    (tmp_path / "s.ply").write_bytes(header + rec.tobytes() + face)
    back = read_point_cloud(tmp_path / "s.ply")
    np.testing.assert_allclose(back.points, pts.astype(float))
    assert back.normals is None


def test_text_with_header_and_extra_columns(tmp_path: Path) -> None:
    (tmp_path / "a.csv").write_text("x,y,z,intensity\n1,2,3,9\n4,5,6,9\n")
    np.testing.assert_allclose(read_point_cloud(tmp_path / "a.csv").points, [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize(
    "name,content,needle",
    [
        ("bad.xyz", "1 2 3\n4 five 6\n", "line 2"),
        ("short.xyz", "1 2 3\n4 5\n", "line 2"),
        ("empty.xyz", "# nothing\n", "no points"),
        ("bad.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n", "end_header"),
        (
            "trunc.ply",
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nend_header\n1 2 3\n",
            "declares 3",
        ),
        ("nan.xyz", "1 2 3\nnan 1 1\n", "non-finite"),
        ("c.las", "x", "unknown point cloud format"),
    ],
)
def test_bad_files_name_the_problem(tmp_path: Path, name: str, content: str, needle: str) -> None:
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(InputError) as exc:
        read_point_cloud(path)
    assert needle in str(exc.value)
    assert name in str(exc.value)


def test_truncated_binary_ply(tmp_path: Path, cloud: np.ndarray) -> None:
    write_point_cloud(tmp_path / "c.ply", cloud)
    raw = (tmp_path / "c.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(raw[:-100])
    with pytest.raises(InputError, match="truncated"):
        read_point_cloud(tmp_path / "t.ply")


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
