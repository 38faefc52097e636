"""Point cloud basics: file I/O, voxel downsampling, normals, crops, outlier removal.

A point cloud is an ``(N, 3)`` float array of points in metres, in whatever frame
the caller names (``points_lidar``, ``points_world``); normals, when present, are a
second ``(N, 3)`` array of unit vectors in the same frame. Every function is
vectorized and uses :class:`scipy.spatial.cKDTree` with all cores for neighbour
searches.

Readers accept PLY (ASCII, binary little- and big-endian, as written by scanners
and by Open3D/CloudCompare/MeshLab) and plain text XYZ/CSV (whitespace- or
comma-separated, optional header line, the first three columns are x, y, z).
Bad files raise :class:`~fabflow.errors.InputError` naming the file and the line.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from fabflow.errors import InputError

FloatArray = NDArray[np.float64]

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Points with optional normals, as read from a file.

    Attributes
    ----------
    points
        ``(N, 3)`` points (metres).
    normals
        ``(N, 3)`` unit normals, or ``None`` when the file has none.
    """

    points: FloatArray
    normals: FloatArray | None = None

    def __len__(self) -> int:
        return len(self.points)


def as_points(points: ArrayLike, name: str = "points") -> FloatArray:
    """Check and convert an ``(N, 3)`` array of finite points.

    Raises
    ------
    InputError
        If the shape is not ``(N, 3)`` or a value is not finite.
    """
    a = np.asarray(points, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{name} must be an (N, 3) array of points, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} holds non-finite values (NaN or inf)")
    return a


# ------------------------------------------------------------------------- reading


def read_point_cloud(path: str | Path) -> PointCloud:
    """Read a point cloud from PLY, XYZ, TXT or CSV.

    Parameters
    ----------
    path
        ``.ply`` (ASCII or binary) or a text file (``.xyz``, ``.txt``, ``.csv``,
        ``.pts``) with x, y, z in its first three columns (metres).

    Returns
    -------
    PointCloud
        The points, and normals when the PLY file has ``nx, ny, nz`` properties.

    Raises
    ------
    InputError
        The file is missing, empty, malformed or holds non-finite coordinates.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("point cloud file does not exist", source=path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        cloud = _read_ply(path)
    elif suffix in (".xyz", ".txt", ".csv", ".pts", ".asc"):
        cloud = PointCloud(_read_text(path))
    else:
        raise InputError(
            f"unknown point cloud format '{suffix}'; expected .ply, .xyz, .txt, .csv or .pts",
            source=path,
        )
    if len(cloud.points) == 0:
        raise InputError("point cloud file holds no points", source=path)
    if not np.all(np.isfinite(cloud.points)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(cloud.points), axis=1))[0])
        raise InputError(f"point {bad} has a non-finite coordinate", source=path)
    return cloud


def _read_text(path: Path) -> FloatArray:
    try:
        lines = path.read_text(encoding="utf-8", errors="strict").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read text point cloud: {exc}", source=path) from None
    rows: list[str] = []
    first_data = None
    for number, line in enumerate(lines, start=1):
        s = line.strip()
        if not s or s.startswith("#") or s.startswith("//"):
            continue
        if first_data is None:
            first_data = number
            if re.match(r"^[A-Za-z_\"']", s):
                continue  # a header line such as "x,y,z,intensity"
        rows.append(s.replace(",", " ").replace(";", " "))
    if not rows:
        return np.zeros((0, 3))
    try:
        data = np.loadtxt(rows, dtype=float, ndmin=2)
    except ValueError:
        data = None
    if data is None or data.shape[1] < 3:
        # find the first offending line for the message
        for number, line in enumerate(lines, start=1):
            s = line.strip()
            if not s or s.startswith(("#", "//")) or (number == first_data and s[0].isalpha()):
                continue
            fields = s.replace(",", " ").replace(";", " ").split()
            try:
                [float(f) for f in fields]
            except ValueError:
                raise InputError(
                    f"expected numbers (x y z ...), got {s[:60]!r}",
                    source=path,
                    location=f"line {number}",
                ) from None
            if len(fields) < 3:
                raise InputError(
                    f"expected at least 3 columns (x y z), got {len(fields)}",
                    source=path,
                    location=f"line {number}",
                )
        raise InputError("rows have differing numbers of columns", source=path)
    return np.ascontiguousarray(data[:, :3])


def _read_ply(path: Path) -> PointCloud:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read PLY file: {exc}", source=path) from None
    if not raw.startswith(b"ply"):
        raise InputError("not a PLY file (missing 'ply' magic on line 1)", source=path)
    end = raw.find(b"end_header")
    if end < 0:
        raise InputError("PLY header has no 'end_header' line", source=path)
    body_start = raw.index(b"\n", end) + 1
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str | None, str]]]] = []
    for number, line in enumerate(header, start=1):
        parts = line.split()
        if not parts or parts[0] in ("ply", "comment", "obj_info"):
            continue
        if parts[0] == "format":
            fmt = parts[1] if len(parts) > 1 else None
        elif parts[0] == "element" and len(parts) == 3 and parts[2].isdigit():
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property" and elements:
            if len(parts) == 5 and parts[1] == "list":
                elements[-1][2].append((parts[4], parts[2], parts[3]))
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                elements[-1][2].append((parts[2], None, parts[1]))
            else:
                raise InputError(
                    f"unsupported PLY property declaration {line.strip()!r}",
                    source=path,
                    location=f"line {number}",
                )
        else:
            raise InputError(
                f"unexpected PLY header line {line.strip()!r}",
                source=path,
                location=f"line {number}",
            )
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(
            f"PLY format {fmt!r} is not ascii, binary_little_endian or binary_big_endian",
            source=path,
        )
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise InputError("PLY file has no 'vertex' element", source=path)
    vi = names.index("vertex")
    _, count, props = elements[vi]
    pnames = [p[0] for p in props]
    for axis in "xyz":
        if axis not in pnames:
            raise InputError(f"PLY vertex element has no '{axis}' property", source=path)
    if any(p[1] is not None for p in props):
        raise InputError("PLY vertex element has a list property", source=path)
    if fmt == "ascii":
        text = raw[body_start:].decode("ascii", errors="replace").splitlines()
        skip = sum(e[1] for e in elements[:vi])
        rows = text[skip : skip + count]
        if len(rows) < count:
            raise InputError(
                f"PLY header declares {count} vertices but the file holds {len(rows)}",
                source=path,
            )
        try:
            data = np.loadtxt(rows, dtype=float, ndmin=2) if count else np.zeros((0, len(props)))
        except ValueError:
            raise InputError(
                "PLY vertex rows are not all numbers with one value per property", source=path
            ) from None
        if data.shape[1] != len(props):
            raise InputError(
                f"PLY vertex rows have {data.shape[1]} values, the header declares {len(props)}",
                source=path,
            )
        cols = {n: data[:, i] for i, n in enumerate(pnames)}
    else:
        if any(p[1] is not None for e in elements[:vi] for p in e[2]):
            raise InputError(
                "binary PLY with list properties before the vertex element", source=path
            )
        order = "<" if fmt == "binary_little_endian" else ">"
        offset = body_start
        for _, n, eprops in elements[:vi]:
            offset += n * int(np.dtype([(p[0], order + _PLY_TYPES[p[2]]) for p in eprops]).itemsize)
        dtype = np.dtype([(p[0], order + _PLY_TYPES[p[2]]) for p in props])
        if len(raw) - offset < count * dtype.itemsize:
            raise InputError(
                f"PLY file is truncated: the header declares {count} vertices "
                f"of {dtype.itemsize} bytes",
                source=path,
            )
        rec = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
        cols = {n: rec[n].astype(float) for n in pnames}
    points = np.column_stack([cols["x"], cols["y"], cols["z"]])
    normals = None
    if all(k in cols for k in ("nx", "ny", "nz")):
        normals = np.column_stack([cols["nx"], cols["ny"], cols["nz"]])
    return PointCloud(points, normals)


# ------------------------------------------------------------------------- writing


def write_point_cloud(
    path: str | Path,
    points: ArrayLike,
    normals: ArrayLike | None = None,
    binary: bool = True,
) -> Path:
    """Write points (and normals) to PLY or to a text XYZ/CSV file.

    Parameters
    ----------
    path
        Target file; ``.ply`` writes PLY (binary little-endian float64 by default,
        ASCII with ``binary=False``), ``.csv`` writes ``x,y,z[,nx,ny,nz]`` with a
        header, anything else space-separated columns.
    points
        ``(N, 3)`` points (metres).
    normals
        Optional ``(N, 3)`` normals.
    binary
        PLY only: binary (default) or ASCII.
    """
    path = Path(path)
    p = as_points(points)
    cols = [p]
    names = ["x", "y", "z"]
    if normals is not None:
        n = as_points(normals, "normals")
        if len(n) != len(p):
            raise InputError("normals must have one row per point")
        cols.append(n)
        names += ["nx", "ny", "nz"]
    data = np.hstack(cols)
    if path.suffix.lower() == ".ply":
        fmt = "binary_little_endian" if binary else "ascii"
        header = (
            f"ply\nformat {fmt} 1.0\ncomment written by fabflow\nelement vertex {len(data)}\n"
            + "".join(f"property double {n}\n" for n in names)
            + "end_header\n"
        )
        with path.open("wb") as fh:
            fh.write(header.encode("ascii"))
            if binary:
                fh.write(np.ascontiguousarray(data, dtype="<f8").tobytes())
            else:
                np.savetxt(fh, data, fmt="%.9g")
    elif path.suffix.lower() == ".csv":
        np.savetxt(path, data, fmt="%.9g", delimiter=",", header=",".join(names), comments="")
    else:
        np.savetxt(path, data, fmt="%.9g")
    return path


# ------------------------------------------------------------------------- filters


def voxel_downsample(
    points: ArrayLike,
    voxel_size: float,
    normals: ArrayLike | None = None,
    min_points: int = 1,
) -> tuple[FloatArray, FloatArray | None]:
    """Replace the points of each occupied voxel by their centroid.

    Parameters
    ----------
    points
        ``(N, 3)`` points (metres).
    voxel_size
        Edge length of the cubic voxels (metres, > 0).
    normals
        Optional ``(N, 3)`` normals, averaged per voxel and re-normalized. The
        average ignores their sign (each is flipped to make its largest component
        positive first), so the returned normals are unoriented.
    min_points
        Voxels holding fewer points are dropped (``n_min`` of paper 002, Table 3).

    Returns
    -------
    points, normals
        The voxel centroids (in order of voxel key) and their normals (or ``None``).
    """
    p = as_points(points)
    if voxel_size <= 0:
        raise InputError(f"voxel_size must be positive, got {voxel_size}")
    if len(p) == 0:
        return p.copy(), None if normals is None else np.zeros((0, 3))
    keys = np.floor((p - p.min(axis=0)) / voxel_size).astype(np.int64)
    span = keys.max(axis=0) + 1
    if np.prod(span.astype(float)) < 2**62:
        flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
        _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    n_vox = len(counts)
    sums = np.stack([np.bincount(inverse, weights=p[:, i], minlength=n_vox) for i in range(3)], 1)
    keep = counts >= min_points
    out = sums[keep] / counts[keep, None]
    out_n = None
    if normals is not None:
        n = np.asarray(normals, dtype=float)
        # sign-invariant average: normals of one surface may point either way (PCA
        # normals of a wall), so flip each to make its largest component positive
        big = np.take_along_axis(n, np.argmax(np.abs(n), axis=1)[:, None], axis=1)
        n = np.where(big < 0, -n, n)
        ns = np.stack([np.bincount(inverse, weights=n[:, i], minlength=n_vox) for i in range(3)], 1)
        ns = ns[keep]
        norm = np.linalg.norm(ns, axis=1, keepdims=True)
        out_n = ns / np.where(norm > 0, norm, 1.0)
    return out, out_n


def estimate_normals(
    points: ArrayLike,
    k: int = 20,
    viewpoint: ArrayLike | None = None,
    tree: cKDTree | None = None,
    return_planarity: bool = False,
) -> FloatArray | tuple[FloatArray, FloatArray]:
    """Surface normals by PCA over the ``k`` nearest neighbours, oriented.

    Parameters
    ----------
    points
        ``(N, 3)`` points (metres), N >= 3.
    k
        Neighbourhood size (including the point itself).
    viewpoint
        Orient every normal towards this point (e.g. the sensor origin, same frame);
        when ``None`` normals point towards +z (horizontal ones keep their sign).
    tree
        A KD-tree over ``points`` to reuse.
    return_planarity
        Also return the surface variation ``l0 / (l0 + l1 + l2)`` per point (0 for a
        perfect plane, 1/3 for isotropic scatter).

    Returns
    -------
    numpy.ndarray or tuple
        ``(N, 3)`` unit normals (and the ``(N,)`` surface variation).
    """
    p = as_points(points)
    if len(p) < 3:
        raise InputError(f"need at least 3 points to estimate normals, got {len(p)}")
    k = int(min(max(k, 3), len(p)))
    tree = tree if tree is not None else cKDTree(p)
    _, idx = tree.query(p, k=k, workers=-1)
    nb = p[idx]
    centred = nb - nb.mean(axis=1, keepdims=True)
    cov = np.matmul(centred.transpose(0, 2, 1), centred) / k
    evals, evecs = np.linalg.eigh(cov)
    normals = evecs[:, :, 0]
    if viewpoint is not None:
        toward = np.asarray(viewpoint, dtype=float).reshape(1, 3) - p
    else:
        toward = np.broadcast_to(np.array([0.0, 0.0, 1.0]), p.shape)
    flip = np.einsum("ij,ij->i", normals, toward) < 0
    normals[flip] *= -1.0
    if return_planarity:
        total = evals.sum(axis=1)
        variation = np.where(total > 0, evals[:, 0] / np.where(total > 0, total, 1.0), 0.0)
        return normals, variation
    return normals


def radius_mask(points: ArrayLike, center: ArrayLike, radius: float) -> NDArray[np.bool_]:
    """Boolean mask of the points within ``radius`` (metres) of ``center``."""
    p = as_points(points)
    d2 = np.sum((p - np.asarray(center, dtype=float).reshape(1, 3)) ** 2, axis=1)
    return d2 <= radius * radius


def crop_radius(points: ArrayLike, center: ArrayLike, radius: float) -> FloatArray:
    """The points within ``radius`` (metres) of ``center`` (a sphere crop)."""
    p = as_points(points)
    return p[radius_mask(p, center, radius)]


def box_mask(points: ArrayLike, lower: ArrayLike, upper: ArrayLike) -> NDArray[np.bool_]:
    """Boolean mask of the points inside the axis-aligned box ``[lower, upper]``."""
    p = as_points(points)
    lo = np.asarray(lower, dtype=float).reshape(1, 3)
    hi = np.asarray(upper, dtype=float).reshape(1, 3)
    return np.all((p >= lo) & (p <= hi), axis=1)


def crop_box(points: ArrayLike, lower: ArrayLike, upper: ArrayLike) -> FloatArray:
    """The points inside the axis-aligned box ``[lower, upper]`` (metres)."""
    p = as_points(points)
    return p[box_mask(p, lower, upper)]


def remove_statistical_outliers(
    points: ArrayLike, k: int = 20, std_ratio: float = 2.0
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Drop points whose mean distance to their neighbours is unusually large.

    A point is kept when its mean distance to its ``k`` nearest neighbours is at
    most ``mean + std_ratio * std`` of that figure over the whole cloud.

    Returns
    -------
    points, mask
        The kept points and the boolean mask of kept points.
    """
    p = as_points(points)
    if len(p) <= k:
        return p.copy(), np.ones(len(p), dtype=bool)
    d, _ = cKDTree(p).query(p, k=k + 1, workers=-1)
    mean_d = d[:, 1:].mean(axis=1)
    keep = mean_d <= mean_d.mean() + std_ratio * mean_d.std()
    return p[keep], keep
