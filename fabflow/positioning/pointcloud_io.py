"""Point cloud files: PLY (ASCII, binary little- and big-endian), XYZ/TXT/CSV/PTS text.

Readers accept PLY as written by scanners and by Open3D/CloudCompare/MeshLab,
and plain text (whitespace-, comma- or semicolon-separated, an optional header
line, ``#`` and ``//`` comments; the first three columns are x, y, z). A file
is read through :mod:`fabflow.files` (a regular file of at most
:data:`MAX_CLOUD_BYTES`) and parsed by numpy at once; it may hold at most
:data:`MAX_CLOUD_POINTS` points, each coordinate finite and within
:data:`MAX_CLOUD_COORDINATE_M`. Every problem is an
:class:`~fabflow.errors.InputError` naming the file and the line (of a text
file or a PLY header) or the vertex (of a binary PLY body).
"""

from __future__ import annotations

import io
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.files import line_at, read_bytes, read_text, show, text_lines
from fabflow.positioning.pointcloud import as_points

FloatArray = NDArray[np.float64]
Locator = Callable[[int], str]
"""Where the k-th point of a file is: ``"line N"`` or ``"vertex N"``."""

MAX_CLOUD_BYTES = 1024 * 2**20
"""Largest point cloud file read (bytes): a binary scan of some 40 million points."""
MAX_CLOUD_POINTS = 50_000_000
"""Most points a file may hold (1.2 GB as coordinates in memory)."""
MAX_CLOUD_COORDINATE_M = 1e7
"""Largest magnitude of a coordinate (metres): projected grid coordinates stay below."""
MAX_PLY_HEADER_BYTES = 65_536
"""Longest PLY header read (bytes); real headers take a few hundred."""
TEXT_SUFFIXES = (".xyz", ".txt", ".csv", ".pts", ".asc")

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
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Points with optional normals, as read from a file.

    Attributes
    ----------
    points
        ``(N, 3)`` points (metres).
    normals
        ``(N, 3)`` unit normals (zero where the file gives a zero vector), or
        ``None`` when the file has none.
    """

    points: FloatArray
    normals: FloatArray | None = None

    def __len__(self) -> int:
        return len(self.points)


def read_point_cloud(path: str | Path) -> PointCloud:
    """Read a point cloud from PLY, XYZ, TXT, CSV, PTS or ASC.

    Parameters
    ----------
    path
        ``.ply`` (ASCII or binary) or a text file with x, y, z in its first
        three columns (metres).

    Returns
    -------
    PointCloud
        The points, and normals when the PLY file has ``nx, ny, nz`` properties
        (scaled to unit length).

    Raises
    ------
    InputError
        The file is missing, not a regular file, too large, empty, malformed,
        or holds a coordinate that is not finite or beyond
        :data:`MAX_CLOUD_COORDINATE_M`; naming the file and the line or vertex.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix != ".ply" and suffix not in TEXT_SUFFIXES:
        raise InputError(
            f"unknown point cloud format {show(suffix, 12)}; expected .ply, "
            + ", ".join(TEXT_SUFFIXES),
            source=path,
        )
    if suffix == ".ply":
        points, normals, where = _read_ply(read_bytes(path, "PLY file", MAX_CLOUD_BYTES), path)
    else:
        points, where = _read_text(path)
        normals = None
    if len(points) == 0:
        raise InputError("point cloud file holds no points", source=path)
    bad = ~np.all(np.isfinite(points), axis=1)
    with np.errstate(invalid="ignore"):
        far = np.abs(points).max(axis=1) > MAX_CLOUD_COORDINATE_M
    for mask, what in ((bad, "is not finite"), (far, f"is beyond {MAX_CLOUD_COORDINATE_M:g} m")):
        if mask.any():
            k = int(np.argmax(mask))
            raise InputError(f"a coordinate of point {k + 1} {what}", path, where(k))
    if normals is not None:
        normals = _unit_normals(normals, path, where)
    return PointCloud(np.ascontiguousarray(points), normals)


def _unit_normals(n: FloatArray, path: Path, where: Locator) -> FloatArray:
    """Normals scaled to unit length (zero ones stay zero); a non-finite one is refused."""
    bad = ~np.all(np.isfinite(n), axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(f"the normal of point {k + 1} is not finite", path, where(k))
    big = np.abs(n).max(axis=1, keepdims=True)
    n = n / np.where(big > 0, big, 1.0)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


# ------------------------------------------------------------------------- text

_NUMBER = re.compile(
    r"[+-]?(?:(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?|nan|inf|infinity)",
    re.ASCII | re.IGNORECASE,
)
"""A number as numpy's text reader takes it (unambiguous: linear on a long token)."""


def _content(line: str) -> list[str]:
    """The fields of a text cloud line (commas and semicolons separate too; comments cut)."""
    body = line.split("#", 1)[0].split("//", 1)[0]
    return body.replace(",", " ").replace(";", " ").split()


def _read_text(path: Path) -> tuple[FloatArray, Locator]:
    """Points of a text cloud, and where its k-th point is (``line N``)."""
    text = read_text(path, "point cloud file", MAX_CLOUD_BYTES)
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    if text.count("\n") > MAX_CLOUD_POINTS + 1000:
        raise InputError(f"more than {MAX_CLOUD_POINTS} lines, the most fabflow reads", path)
    content = re.compile(r"^[ \t]*(?!#|//)\S.*$", re.MULTILINE)
    first = content.search(text)
    if first is not None and re.match(r"[ \t]*[A-Za-z_\"']", first.group()):
        text = text[: first.start()] + text[first.end() :]  # a header such as "x,y,z,intensity"
        first = content.search(text, first.start())
    if first is None:
        return np.zeros((0, 3)), str
    clean = text.replace(",", " ").replace(";", " ")
    try:
        data = np.loadtxt(
            io.StringIO(clean), comments=("#", "//"), usecols=(0, 1, 2), ndmin=2, dtype=float
        )
    except ValueError:
        raise _text_problem(clean, path) from None

    def where(k: int) -> str:
        numbers = (n for n, line in enumerate(text_lines(clean), 1) if _content(line))
        return f"line {next(n for i, n in enumerate(numbers) if i == k)}"

    return data, where


def _text_problem(text: str, path: Path) -> InputError:
    """The error of the first line numpy cannot read as x y z (found line by line)."""
    for number, line in enumerate(text_lines(text), start=1):
        fields = _content(line)
        if not fields:
            continue
        if len(fields) < 3:
            return InputError(
                f"expected at least 3 columns (x y z), got {len(fields)}", path, f"line {number}"
            )
        bad = next((f for f in fields[:3] if not _NUMBER.fullmatch(f)), None)
        if bad is not None:
            return InputError(f"{show(bad)} is not a number", path, f"line {number}")
    return InputError("not columns of numbers (x y z ...)", path)


# ------------------------------------------------------------------------- PLY


@dataclass
class _Element:
    name: str
    count: int
    line: int
    props: list[tuple[str, str | None, str]]
    """``(name, list count type or None, value type)`` per property."""


def _ply_header(raw: bytes, path: Path) -> tuple[str, list[_Element], int]:
    """Format, elements and the offset of the body of a PLY file."""
    if not re.match(rb"ply\r?\n", raw):
        raise InputError("not a PLY file (line 1 is not 'ply')", path, "line 1")
    window = raw[: MAX_PLY_HEADER_BYTES + 2]
    end = re.search(rb"(?m)^end_header[ \t]*(\r?\n|\Z)", window)
    if end is not None and not end.group(1) and len(window) < len(raw):
        end = None  # the window ends right after "end_header": its line goes on
    if end is None:
        raise InputError(
            f"no 'end_header' line in the first {MAX_PLY_HEADER_BYTES} bytes", path, "line 1"
        )
    head = raw[: end.start()]
    try:
        lines = text_lines(head.decode("ascii"))
    except UnicodeDecodeError as exc:
        raise InputError(
            "a PLY header is ASCII text", path, f"line {line_at(raw, exc.start)}"
        ) from None
    fmt = None
    elements: list[_Element] = []
    for number, line in enumerate(lines, start=1):
        parts = line.split()
        at = f"line {number}"
        if not parts or parts[0] in ("ply", "comment", "obj_info"):
            continue
        if parts[0] == "format" and len(parts) == 3:
            fmt = parts[1]
        elif parts[0] == "element" and len(parts) == 3:
            if not (parts[2].isascii() and parts[2].isdigit()):
                raise InputError(f"element count {show(parts[2], 20)} is not a count", path, at)
            if len(parts[2]) > 12 or int(parts[2]) > 10 * MAX_CLOUD_POINTS:
                raise InputError(f"element count {show(parts[2], 20)} is too large", path, at)
            elements.append(_Element(parts[1], int(parts[2]), number, []))
        elif parts[0] == "property" and elements:
            if len(parts) == 5 and parts[1] == "list" and {parts[2], parts[3]} <= set(_PLY_TYPES):
                prop = (parts[4], parts[2], parts[3])
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                prop = (parts[2], None, parts[1])
            else:
                raise InputError(f"unsupported PLY property {show(line.strip())}", path, at)
            if any(p[0] == prop[0] for p in elements[-1].props):
                raise InputError(f"property {show(prop[0])} appears twice", path, at)
            elements[-1].props.append(prop)
        else:
            raise InputError(f"unexpected PLY header line {show(line.strip())}", path, at)
    if fmt not in _FORMATS:
        raise InputError(
            f"PLY format {show(str(fmt))} is not one of {', '.join(_FORMATS)}", path, "line 2"
        )
    return fmt, elements, end.end()


def _read_ply(raw: bytes, path: Path) -> tuple[FloatArray, FloatArray | None, Locator]:
    """Points (and normals) of a PLY file, and where its k-th vertex is."""
    fmt, elements, body = _ply_header(raw, path)
    vi = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if vi is None:
        raise InputError("PLY file has no 'vertex' element", path)
    vertex = elements[vi]
    at = f"line {vertex.line}"
    names = [p[0] for p in vertex.props]
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise InputError(f"PLY vertex element has no '{missing[0]}' property", path, at)
    if any(p[1] is not None for p in vertex.props):
        raise InputError("PLY vertex element has a list property", path, at)
    if vertex.count > MAX_CLOUD_POINTS:
        raise InputError(
            f"the header declares {show(str(vertex.count), 20)} vertices, more than the "
            f"{MAX_CLOUD_POINTS} fabflow reads",
            path,
            at,
        )
    if fmt == "ascii":
        data, where = _ply_ascii(raw, body, elements, vi, path)
    else:
        data = _ply_binary(raw, body, elements, vi, fmt, path)

        def where(k: int) -> str:
            return f"vertex {k + 1}"

    cols = {n: data[:, i] for i, n in enumerate(names)}
    points = np.column_stack([cols["x"], cols["y"], cols["z"]])
    normals = None
    if all(k in cols for k in ("nx", "ny", "nz")):
        normals = np.column_stack([cols["nx"], cols["ny"], cols["nz"]])
    return points, normals, where


def _ply_ascii(
    raw: bytes, body: int, elements: list[_Element], vi: int, path: Path
) -> tuple[FloatArray, Locator]:
    """The vertex rows of an ASCII PLY body as floats (one column per property)."""
    vertex = elements[vi]
    n_props = len(vertex.props)
    first_line = line_at(raw, body)
    try:
        text = raw[body:].decode("ascii")
    except UnicodeDecodeError as exc:
        raise InputError(
            "the body of an ASCII PLY file is ASCII text", path, f"line {line_at(raw, exc.start)}"
        ) from None
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    skip = sum(e.count for e in elements[:vi])

    def where(k: int) -> str:
        return f"line {first_line + skip + k}"

    if text.count("\n") + 1 < skip + vertex.count:
        raise InputError(
            f"the header declares {vertex.count} vertices (after {skip} other rows) but the "
            f"file holds {max(text.count(chr(10)) + 1 - skip, 0)} lines of them",
            path,
            f"line {vertex.line}",
        )
    if vertex.count == 0:
        return np.zeros((0, n_props)), where
    try:
        data = np.loadtxt(
            io.StringIO(text), skiprows=skip, max_rows=vertex.count, ndmin=2, comments=None
        )
    except ValueError:
        lines = text_lines(text)[skip : skip + vertex.count]
        for k, line in enumerate(lines):
            fields = line.split()
            if len(fields) != n_props:
                raise InputError(
                    f"expected {n_props} values (one per vertex property), got {len(fields)}",
                    path,
                    where(k),
                ) from None
            bad = next((f for f in fields if not _NUMBER.fullmatch(f)), None)
            if bad is not None:
                raise InputError(f"{show(bad)} is not a number", path, where(k)) from None
        raise InputError("PLY vertex rows are not numbers", path, f"line {vertex.line}") from None
    if data.shape != (vertex.count, n_props):
        raise InputError(
            f"the header declares {vertex.count} vertices of {n_props} values; the rows "
            f"hold {data.shape[0]} of {data.shape[1]}",
            path,
            f"line {vertex.line}",
        )
    return data, where


def _ply_binary(
    raw: bytes, body: int, elements: list[_Element], vi: int, fmt: str, path: Path
) -> FloatArray:
    """The vertex records of a binary PLY body as floats (one column per property)."""
    if any(p[1] is not None for e in elements[:vi] for p in e.props):
        raise InputError(
            "binary PLY with list properties before the vertex element",
            path,
            f"line {elements[vi].line}",
        )
    order = "<" if fmt == "binary_little_endian" else ">"

    def dtype(e: _Element) -> np.dtype:
        return np.dtype([(p[0], order + _PLY_TYPES[p[2]]) for p in e.props])

    offset = body + sum(e.count * dtype(e).itemsize for e in elements[:vi])
    vertex = elements[vi]
    size = dtype(vertex).itemsize
    if offset + vertex.count * size > len(raw):
        raise InputError(
            f"PLY file is truncated: the header declares {vertex.count} vertices of {size} "
            f"bytes, the file holds {max(len(raw) - offset, 0)} bytes for them",
            path,
            f"line {vertex.line}",
        )
    rec = np.frombuffer(raw, dtype=dtype(vertex), count=vertex.count, offset=offset)
    return np.column_stack([rec[p[0]].astype(float) for p in vertex.props])


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
