"""Point cloud files: round trips, PLY variants, and bad files named with their line or vertex."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from fabflow.errors import InputError
from fabflow.positioning.pointcloud_io import read_point_cloud, write_point_cloud


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
        ("nan.xyz", "1 2 3\nnan 1 1\n", "line 2: a coordinate of point 2 is not finite"),
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


PLY_HEAD = "ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
PLY_HEAD += "property float z\nend_header"
TWICE = PLY_HEAD.replace("float y", "float x").format(fmt="ascii", n=1)
LATIN = PLY_HEAD.replace("ply\n", "ply\ncomment \xe9\n").format(fmt="ascii", n=0)
NO_END = PLY_HEAD.format(fmt="ascii", n=1).replace("end_header", "end_headerX")


def test_end_header_without_a_final_newline(tmp_path: Path) -> None:
    path = tmp_path / "h.ply"
    path.write_text(PLY_HEAD.format(fmt="ascii", n=0))
    with pytest.raises(InputError, match="holds no points"):
        read_point_cloud(path)
    path.write_text(PLY_HEAD.format(fmt="binary_little_endian", n=2))
    with pytest.raises(InputError, match="truncated") as exc:
        read_point_cloud(path)
    assert exc.value.location == "line 3"
    path.write_bytes(
        PLY_HEAD.format(fmt="binary_little_endian", n=1).encode()
        + b"\r\n"
        + np.array([1, 2, 3], "<f4").tobytes()
    )
    np.testing.assert_allclose(read_point_cloud(path).points, [[1, 2, 3]])


@pytest.mark.parametrize(
    ("header", "body", "what", "where"),
    [
        (PLY_HEAD.format(fmt="binary_little_endian", n=10**8), b"", "more than the", "line 3"),
        (PLY_HEAD.format(fmt="binary_big_endian", n="9" * 400), b"", "too large", "line 3"),
        (PLY_HEAD.format(fmt="binary_big_endian", n=-1), b"", "is not a count", "line 3"),
        (PLY_HEAD.format(fmt="ascii", n=3), b"1 2 3\n4 5 6\n", "declares 3 vertices", "line 3"),
        (PLY_HEAD.format(fmt="ascii", n=2), b"1 2 3\n4 x 6\n", "'x' is not a number", "line 9"),
        (PLY_HEAD.format(fmt="ascii", n=2), b"1 2 3\n4 6\n", "expected 3 values", "line 9"),
        (TWICE, b"1 2 3\n", "twice", "line 5"),
        (LATIN, b"", "ASCII", "line 2"),
        (NO_END, b"", "no 'end_header'", "line 1"),
    ],
)
def test_bad_ply_headers_and_bodies(
    tmp_path: Path, header: str, body: bytes, what: str, where: str
) -> None:
    path = tmp_path / "b.ply"
    path.write_bytes(header.encode("latin-1") + b"\n" + body)
    with pytest.raises(InputError, match=what) as exc:
        read_point_cloud(path)
    assert exc.value.location == where and "9" * 50 not in str(exc.value)


def test_non_finite_and_far_points_name_their_vertex_or_line(tmp_path: Path) -> None:
    pts = np.array([[0, 0, 0], [1, np.inf, 0], [2, 2, 2]], dtype="<f4")
    path = tmp_path / "inf.ply"
    path.write_bytes(
        PLY_HEAD.format(fmt="binary_little_endian", n=3).encode() + b"\n" + pts.tobytes()
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(InputError, match="point 2 is not finite") as exc:
            read_point_cloud(path)
    assert exc.value.location == "vertex 2"
    (tmp_path / "far.xyz").write_text("# scan\nx y z\n1 2 3\n\n1 2 3e9\n")
    with pytest.raises(InputError, match="beyond 1e\\+07 m") as exc:
        read_point_cloud(tmp_path / "far.xyz")
    assert exc.value.location == "line 5"
    (tmp_path / "long.xyz").write_text("1 2 3\n1 2 " + "9" * 200_000 + "\n")
    with pytest.raises(InputError, match="not finite") as exc:
        read_point_cloud(tmp_path / "long.xyz")
    assert exc.value.location == "line 2"


def test_normals_are_checked_and_scaled(tmp_path: Path) -> None:
    path = tmp_path / "n.ply"
    write_point_cloud(path, np.eye(3), np.array([[0, 0, 2.0], [0, 0, 0], [1e300, 1e300, 0]]))
    cloud = read_point_cloud(path)
    np.testing.assert_allclose(cloud.normals, [[0, 0, 1], [0, 0, 0], [0.5**0.5, 0.5**0.5, 0]])
    head = "ply\nformat ascii 1.0\nelement vertex 1\n" + "".join(
        f"property float {n}\n" for n in ("x", "y", "z", "nx", "ny", "nz")
    )
    path.write_text(head + "end_header\n1 2 3 0 nan 1\n")
    with pytest.raises(InputError, match="normal of point 1 is not finite") as exc:
        read_point_cloud(path)
    assert exc.value.location == "line 11"


def test_devices_and_pipes_are_refused(tmp_path: Path) -> None:
    fifo = tmp_path / "scan.xyz"
    os.mkfifo(fifo)
    device = tmp_path / "zero.ply"
    device.symlink_to("/dev/zero")
    for path in (fifo, device):
        with pytest.raises(InputError, match="not a regular file"):
            read_point_cloud(path)  # either would block or never end if read
