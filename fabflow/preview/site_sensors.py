"""What the localization puts on the site, drawn into a preview scene (world frame).

UWB anchors, the total station's set-ups (the project's given one, or those the
localized visits were measured from) with their control points, and the ICP map.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from fabflow.errors import InputError
from fabflow.localize.setups import control_points
from fabflow.preview.model import PreviewModel
from fabflow.project import Project, TotalStationSetup
from fabflow.transforms.so3 import quat_from_matrix


def instrument_setups(project: Project, model: PreviewModel) -> list[tuple[str, np.ndarray]]:
    """The total station's set-ups to draw: the project's given one, else those the
    localized visits were measured from (id, 4x4 pose)."""
    loc = project.localization
    if loc.total_station is not None and loc.total_station.T_world_instrument is not None:
        return [("T1", loc.total_station.T_world_instrument.matrix())]
    seen: dict[str, np.ndarray] = {}
    for pose in model.localization.values():
        q = pose.quality
        if "instrument_setup" in q and "T_world_instrument" in q:
            seen.setdefault(str(q["instrument_setup"]), np.asarray(q["T_world_instrument"]))
    return list(seen.items())


def add_localization(scene: Any, project: Project, model: PreviewModel) -> None:
    """Draw the UWB anchors, the total station's set-ups with their control points and the
    ICP map of ``project`` (world frame) into the viser ``scene``."""
    loc = project.localization
    if loc.uwb is not None and loc.uwb.anchors:
        T_wu = loc.uwb.T_world_uwb.matrix()
        names = list(loc.uwb.anchors)
        p = np.array([loc.uwb.anchors[n] for n in names], dtype=float)
        p = p @ T_wu[:3, :3].T + T_wu[:3, 3]
        sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.06)
        scene.add_batched_meshes_simple(
            "/localization/uwb_anchors",
            vertices=sphere.vertices,
            faces=sphere.faces,
            batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (len(names), 1)),
            batched_positions=p,
            batched_colors=(200, 40, 160),
            lod="off",
        )
        for name, pos in zip(names, p, strict=True):
            scene.add_label(f"/localization/uwb_labels/{name}", text=name, position=tuple(pos))
    setups = instrument_setups(project, model)
    for name, T in setups:
        node = f"/localization/total_station/{name}"
        scene.add_frame(
            node,
            axes_length=0.3,
            axes_radius=0.01,
            wxyz=tuple(quat_from_matrix(T[:3, :3])),
            position=tuple(T[:3, 3]),
        )
        scene.add_cylinder(
            f"{node}/tripod",
            radius=0.03,
            height=float(T[2, 3]),
            color=(240, 200, 0),
            position=(0.0, 0.0, -float(T[2, 3]) / 2),
        )
        instrument = (loc.total_station or TotalStationSetup()).instrument
        scene.add_label(f"{node}/label", text=f"{name}: total station ({instrument})")
    ts = loc.total_station
    if setups and (ts is None or ts.T_world_instrument is None):
        for name, xyz in control_points(project).items():
            scene.add_icosphere(
                f"/localization/control_points/{name}",
                radius=0.05,
                color=(240, 120, 0),
                position=tuple(float(v) for v in xyz),
            )
            scene.add_label(
                f"/localization/control_points/{name}/label", text=f"control point {name}"
            )
    if loc.icp is not None and loc.icp.map is not None:
        pts = _load_points(loc.icp.map)
        if pts.size:
            scene.add_point_cloud(
                "/localization/icp_map",
                points=pts.astype(np.float32),
                colors=(90, 140, 200),
                point_size=0.02,
                precision="float32",
            )


def _load_points(path: Any) -> np.ndarray:
    """(N, 3) points of a PLY/XYZ/PCD point-cloud file, empty if it cannot be read."""
    path = Path(path)
    if path.suffix.lower() in (".xyz", ".txt", ".csv"):
        delimiter = "," if path.suffix.lower() == ".csv" else None
        try:
            data = np.loadtxt(path, delimiter=delimiter, ndmin=2)
        except ValueError as exc:
            raise InputError(f"cannot read point cloud: {exc}", source=path) from None
        return data[:, :3]
    try:
        cloud = trimesh.load(path)
    except Exception as exc:
        raise InputError(f"cannot read point cloud: {exc}", source=path) from None
    return np.asarray(getattr(cloud, "vertices", np.zeros((0, 3))), dtype=float)
