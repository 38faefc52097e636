"""Fuzz: point clouds (PLY ASCII and binary, XYZ, CSV), damaged, are read or refused cleanly."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from reader_mutations import check_reader, fuzz_settings, mutated

from fabflow.positioning.pointcloud_io import read_point_cloud, write_point_cloud


def _samples() -> list[tuple[bytes, str]]:
    rng = np.random.default_rng(7)
    points = rng.uniform(-3.0, 3.0, (40, 3))
    normals = np.tile([0.0, 0.0, 1.0], (40, 1))
    out = []
    with tempfile.TemporaryDirectory() as folder:
        for name, binary in (("b.ply", True), ("a.ply", False), ("c.xyz", False), ("d.csv", 0)):
            path = Path(folder) / name
            ply = name.endswith(".ply")
            write_point_cloud(path, points, normals if ply else None, binary)
            out.append((path.read_bytes(), path.suffix))
    header = b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\n"
    header += b"property float y\nproperty float z\nelement face 1\n"
    header += b"property list uchar int vertex_indices\nend_header"
    body = np.arange(6, dtype=">f4").tobytes() + b"\x03" + np.arange(3, dtype=">i4").tobytes()
    out.append((header + b"\n" + body, ".ply"))
    out.append((header, ".ply"))  # no body, and no newline after end_header
    return out


SAMPLES = _samples()


@st.composite
def clouds(draw: st.DrawFn) -> tuple[bytes, str]:
    data, suffix = draw(st.sampled_from(SAMPLES))
    binary = suffix == ".ply" and b"binary" in data[:60]
    return draw(mutated(data, line_ops=not binary)), suffix


@fuzz_settings(100)
@given(clouds())
def test_point_cloud_files(case: tuple[bytes, str]) -> None:
    data, suffix = case
    cloud = check_reader(read_point_cloud, data, suffix)
    if cloud is not None:
        assert cloud.points.ndim == 2 and cloud.points.shape[1] == 3 and len(cloud) > 0
