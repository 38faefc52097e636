"""Print paths: layers of contours, tool frames and constant-speed Hermite sampling.

A printed layer is one polyline (the *waypoints*) in its element frame, with a
flag per segment telling whether the extruder is on (printing a contour) or off
(travelling between contours). The path of the tool between waypoints is a
cubic Hermite curve whose tangent at every waypoint is the bisector of the two
adjacent segment directions (so the tangent is continuous), sampled at a fixed
rate (100 Hz) at constant tool speed, as in the excavator printing paper
(seeds 000, section IV-B).

The Hermite curve of a segment of length ``d`` whose end tangents make angles
``a0`` and ``a1`` with the chord stays within ``4/27 * d * (sin a0 + sin a1)`` of
the chord. Waypoints are added on the segments next to every bend until that
bound is below ``tol`` everywhere, so the sampled path stays within ``tol`` of
the drawn polyline (0.25 mm by default, half the allowed 0.5 mm).

Tool frames: z axis pointing down (against the layer's up axis), x along the
path, y = z cross x.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fabflow.design.dxf_in import Contour, read_dxf_contours
from fabflow.design.elements import Element
from fabflow.design.hermite import SampledPath, polyline_tangents, sample_hermite
from fabflow.design.specs import PrintPathSpec
from fabflow.errors import InputError
from fabflow.schema import Limits
from fabflow.transforms.se3 import make_T

if TYPE_CHECKING:
    import trimesh


@dataclass(frozen=True)
class LayerPath:
    """The waypoints of one printed layer.

    Attributes
    ----------
    points
        (N, 3) waypoints (metres) in the layer's frame.
    extrude
        (N - 1,) whether the extruder is on along each segment.
    """

    points: np.ndarray
    extrude: np.ndarray

    @property
    def print_length(self) -> float:
        """Length of the extruding segments (metres)."""
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        return float(seg[self.extrude].sum())

    @property
    def travel_length(self) -> float:
        """Length of the travel segments (metres)."""
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        return float(seg[~self.extrude].sum())


def tool_frames(
    points: np.ndarray, tangents: np.ndarray, up: np.ndarray | None = None
) -> np.ndarray:
    """Tool frames along a path: z down (against ``up``), x along the path.

    Parameters
    ----------
    points
        (N, 3) tool positions (metres).
    tangents
        (N, 3) directions of travel (need not be unit length).
    up
        The up direction of the frame the points are in; (0, 0, 1) by default.

    Returns
    -------
    numpy.ndarray
        (N, 4, 4) poses ``T_frame_tool``. Where the tangent is vertical the x
        axis falls back to the frame's x axis.
    """
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=float)
    z = -up / np.linalg.norm(up)
    x = np.asarray(tangents, dtype=float) - np.outer(np.asarray(tangents) @ z, z)
    norm = np.linalg.norm(x, axis=1)
    flat = norm < 1e-12
    if flat.any():
        fallback = np.array([1.0, 0.0, 0.0]) - z[0] * z
        x[flat] = fallback
        norm[flat] = np.linalg.norm(fallback)
    x /= norm[:, None]
    y = np.cross(np.broadcast_to(z, x.shape), x)
    R = np.stack([x, y, np.broadcast_to(z, x.shape)], axis=2)
    return make_T(R, np.asarray(points, dtype=float))


def order_contours(
    contours: list[np.ndarray], closed: list[bool], start: np.ndarray | None = None
) -> LayerPath:
    """Join contours into one layer path, nearest contour next, with travel moves between.

    A closed contour starts (its seam) at the vertex nearest to where the tool
    is; an open contour is reversed when its far end is nearer.

    Parameters
    ----------
    contours
        (N_i, 3) vertex arrays; closed ones repeat the first vertex at the end.
    closed
        Whether each contour is closed.
    start
        Where the tool starts (metres); the origin when omitted.
    """
    pos = np.zeros(3) if start is None else np.asarray(start, dtype=float)
    remaining = list(range(len(contours)))
    pts: list[np.ndarray] = []
    ext: list[np.ndarray] = []
    while remaining:
        best, best_d, best_k, best_rev = -1, np.inf, 0, False
        for i in remaining:
            c = contours[i]
            if closed[i]:
                d = np.linalg.norm(c[:-1] - pos, axis=1)
                k = int(np.argmin(d))
                cand = (d[k], k, False)
            else:
                d0, d1 = np.linalg.norm(c[0] - pos), np.linalg.norm(c[-1] - pos)
                cand = (d0, 0, False) if d0 <= d1 else (d1, 0, True)
            if cand[0] < best_d:
                best, (best_d, best_k, best_rev) = i, cand
        c = contours[best]
        if closed[best]:
            c = np.vstack([np.roll(c[:-1], -best_k, axis=0), c[best_k : best_k + 1]])
        elif best_rev:
            c = c[::-1]
        if pts:
            ext.append(np.array([False]))
        pts.append(c)
        ext.append(np.ones(len(c) - 1, dtype=bool))
        pos = c[-1]
        remaining.remove(best)
    points = np.vstack(pts)
    extrude = np.concatenate(ext)
    # the travel move joins the last vertex of one contour to the first of the next
    return LayerPath(points=points, extrude=extrude)


def mesh_layer_count(
    mesh: trimesh.Trimesh, layer_height: float, n_layers: int | None = None
) -> int:
    """Number of layers :func:`slice_mesh` cuts: the mesh's height in ``layer_height`` steps."""
    z0, z1 = mesh.bounds[:, 2]
    n = int(np.floor((z1 - z0) / layer_height + 1e-9))
    return n if n_layers is None else min(n, n_layers)


def slice_mesh(
    mesh: trimesh.Trimesh, layer_height: float, n_layers: int | None = None
) -> list[tuple[float, list[np.ndarray]]]:
    """Slice a mesh into closed contours, one set per layer.

    Layer ``k`` is cut at ``z_min + (k + 0.5) * layer_height`` (the middle of the
    layer, where the printed bead's cross-section is taken).

    Returns
    -------
    list of (z, contours)
        The cut height (mesh frame, metres) and the closed contours there, each
        (N, 3) with the first vertex repeated at the end.
    """
    z0 = mesh.bounds[0, 2]
    n = mesh_layer_count(mesh, layer_height, n_layers)
    heights = (np.arange(n) + 0.5) * layer_height
    sections = mesh.section_multiplane(
        plane_origin=[0.0, 0.0, z0], plane_normal=[0.0, 0.0, 1.0], heights=heights
    )
    out = []
    for h, sec in zip(heights, sections, strict=True):
        contours = []
        if sec is not None:
            to_3d = sec.metadata["to_3D"]
            for d in sec.discrete:
                p3 = np.column_stack([d, np.zeros(len(d))]) @ to_3d[:3, :3].T + to_3d[:3, 3]
                p3 = _drop_collinear(p3)
                if len(p3) >= 4:
                    contours.append(p3)
        out.append((float(z0 + h), contours))
    return out


def _drop_collinear(closed_pts: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Remove vertices of a closed polyline that lie on the line through their neighbours."""
    ring = closed_pts[:-1]
    prev, nxt = np.roll(ring, 1, axis=0), np.roll(ring, -1, axis=0)
    cross = np.linalg.norm(np.cross(ring - prev, nxt - ring), axis=1)
    keep = cross > tol * np.linalg.norm(nxt - prev, axis=1)
    ring = ring[keep]
    return np.vstack([ring, ring[:1]])


def _load_mesh(path: Path, factor: float) -> trimesh.Trimesh:
    import trimesh  # heavy; only mesh sources need it

    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(f"cannot read mesh: {exc}", path) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("the file holds no triangle mesh", path)
    if not mesh.is_watertight:
        raise InputError("the mesh is not watertight (its slices would not be closed)", path)
    mesh.apply_scale(factor)
    return mesh


_MESH_UNITS = {"auto": 1.0, "m": 1.0, "cm": 0.01, "mm": 1e-3, "in": 0.0254, "ft": 0.3048}


def _check_samples(
    spec: PrintPathSpec, layers: list[tuple[float, LayerPath, bool]], limits: Limits, source: Path
) -> None:
    """Refuse print paths whose samples exceed ``limits.max_path_samples``.

    A layer has its waypoints plus ``length * sample_rate_hz / speed`` samples
    (what :func:`sample_print_path` makes of it).
    """
    distinct = {id(path): path for _, path, _ in layers}
    times = Counter(id(path) for _, path, _ in layers)
    waypoints = sum(len(p.points) * times[k] for k, p in distinct.items())
    length = sum((p.print_length + p.travel_length) * times[k] for k, p in distinct.items())
    samples = waypoints + length * spec.sample_rate_hz / spec.speed
    if samples > limits.max_path_samples:
        raise InputError(
            f"the {len(layers)} print path layers ({length:.6g} m of path, {waypoints} "
            f"waypoints) at {spec.sample_rate_hz:g} Hz and {spec.speed:g} m/s make "
            f"{samples:.3g} samples, more than limits.max_path_samples = "
            f"{limits.max_path_samples}; raise it in the project's 'limits' section if "
            "this is meant",
            source,
        )


def _mesh_layers(
    spec: PrintPathSpec, limits: Limits
) -> tuple[float, list[tuple[float, LayerPath, bool]]]:
    """The lowest point of the mesh and its layers, refused beyond ``limits.max_elements``."""
    assert spec.mesh is not None
    mesh = _load_mesh(spec.mesh, _MESH_UNITS[spec.units])
    n_layers = spec.n_layers if "n_layers" in spec.model_fields_set else None
    n = mesh_layer_count(mesh, spec.layer_height, n_layers)
    if n > limits.max_elements:
        raise InputError(
            f"slicing the mesh every {spec.layer_height:g} m makes {n} layers, more than "
            f"limits.max_elements = {limits.max_elements}",
            spec.mesh,
        )
    if n == 0:
        raise InputError(
            f"the mesh is lower than one layer ({spec.layer_height:g} m): nothing to print",
            spec.mesh,
        )
    z0 = float(mesh.bounds[0, 2])
    layers = []
    for k, (z_cut, rings) in enumerate(slice_mesh(mesh, spec.layer_height, n_layers)):
        if not rings:
            raise InputError(f"the mesh has no cross-section at z = {z_cut:.4f} m", spec.mesh)
        flat = [np.column_stack([r[:, :2], np.zeros(len(r))]) for r in rings]
        layers.append(
            (z0 + (k + 1) * spec.layer_height, order_contours(flat, [True] * len(flat)), True)
        )
    return z0, layers


def print_path_elements(
    spec: PrintPathSpec, id_start: int = 0, source_index: int = 0, limits: Limits | None = None
) -> list[Element]:
    """One ``print_path`` element per printed layer.

    Parameters
    ----------
    spec
        The print path source (a DXF drawing or a mesh).
    id_start
        Number of the first element id (``"P000"`` for 0).
    source_index
        Index of the source in ``project.elements`` (recorded in the attributes).
    limits
        The project's limits (default :class:`~fabflow.schema.Limits`): mesh layers
        and path samples are checked before the elements are made.

    Returns
    -------
    list of Element
        Layer ``k``: element frame at the drawing origin raised to the top of the
        layer, ``(k + 1) * layer_height``; ``polyline`` the layer's waypoints in
        that frame; ``supports`` the layer below.

    Raises
    ------
    InputError
        A bad drawing or mesh, or more layers or samples than ``limits`` allow.
    """
    limits = Limits() if limits is None else limits
    T_world_origin = spec.origin.matrix()
    common = {
        "layer_height": spec.layer_height,
        "bead_width": spec.bead_width,
        "speed": spec.speed,
        "sample_rate_hz": spec.sample_rate_hz,
        "source_index": source_index,
    }
    layers: list[tuple[float, LayerPath, bool]] = []
    if spec.dxf is not None:
        contours: list[Contour] = read_dxf_contours(
            spec.dxf, spec.layers, spec.units, require_closed=spec.closed
        )
        layer_path = order_contours([c.points for c in contours], [c.closed for c in contours])
        all_closed = all(c.closed for c in contours)
        layers = [
            ((k + 1) * spec.layer_height, layer_path, all_closed) for k in range(spec.n_layers)
        ]
        common["source"] = spec.dxf.name
        common["dxf_layers"] = sorted({c.layer for c in contours})
        source = spec.dxf
    else:
        assert spec.mesh is not None
        _, layers = _mesh_layers(spec, limits)
        common["source"] = spec.mesh.name
        source = spec.mesh
    _check_samples(spec, layers, limits, source)
    elements = []
    for k, (z, path, all_closed) in enumerate(layers):
        T_origin_layer = np.eye(4)
        T_origin_layer[2, 3] = z
        elements.append(
            Element(
                id=f"P{id_start + k:03d}",
                type="print_path",
                T_world_element=T_world_origin @ T_origin_layer,
                layer=k,
                supports=() if k == 0 else (f"P{id_start + k - 1:03d}",),
                part=None,
                robot_built=True,
                polyline=path.points,
                attributes={
                    **common,
                    "closed": all_closed,
                    "extrude": path.extrude.tolist(),
                    "length": path.print_length,
                    "travel_length": path.travel_length,
                },
            )
        )
    return elements


def element_tool_frames(element: Element) -> np.ndarray:
    """Tool frames in the world at the waypoints of a print path element.

    Returns
    -------
    numpy.ndarray
        (N, 4, 4) ``T_world_tool``: z down, x along the path.
    """
    if element.polyline is None:
        raise ValueError(f"element {element.id} has no polyline")
    T_el = tool_frames(element.polyline, polyline_tangents(element.polyline))
    return element.T_world_element @ T_el


def sample_print_path(element: Element, tol: float = 2.5e-4) -> tuple[SampledPath, np.ndarray]:
    """Sample a print path element at its rate and speed.

    Returns
    -------
    sampled, T_world_tool
        The samples (in the element frame) and the (M, 4, 4) tool frames in the world.
    """
    if element.polyline is None:
        raise ValueError(f"element {element.id} has no polyline")
    attrs = element.attributes
    extrude = np.asarray(attrs.get("extrude", np.ones(len(element.polyline) - 1)), dtype=bool)
    sampled = sample_hermite(
        element.polyline,
        float(attrs.get("speed", 0.1)),
        float(attrs.get("sample_rate_hz", 100.0)),
        extrude,
        tol,
    )
    return sampled, element.T_world_element @ tool_frames(sampled.points, sampled.tangents)
