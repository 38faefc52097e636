"""Robots defined in project files for the tests: the KR 60-3 as OPW, DH and URDF.

Importable as ``custom_robots`` from any test folder (like ``helpers``).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from helpers import PROJECTS

from fabflow.robots.catalog import get_robot
from fabflow.transforms.so3 import abc_from_matrix

KR60_OPW: dict[str, Any] = {
    "a1": 0.350,
    "a2": -0.145,
    "b": 0.0,
    "c1": 0.815,
    "c2": 0.850,
    "c3": 0.820,
    "c4": 0.170,
    "offsets_deg": [0, -90, 0, 0, 0, 0],
    "signs": [-1, 1, 1, -1, 1, -1],
}
"""The KR 60-3's OPW parameters, as ``KR60_3_OPW`` (offsets in degrees)."""

KR60_DH: dict[str, Any] = {
    "a": [0.350, 0.850, 0.145, 0, 0, 0],
    "alpha_deg": [-90, 0, -90, 90, -90, 0],
    "d": [0.815, 0, 0, 0.820, 0, 0.170],
    "offset_deg": [0, 0, -90, 0, 0, 180],
    "joint_sign": [-1, 1, 1, -1, 1, -1],
}
"""The KR 60-3's DH table, as the catalogue's."""

KR60_CAPSULES: list[dict[str, Any]] = [
    {"name": "base", "frame_a": 0, "p_a": [0, 0, 0.30], "frame_b": 0, "p_b": [0, 0, 0.25],
     "radius": 0.30},
    {"name": "carousel", "frame_a": 0, "p_a": [0, 0, 0.45], "frame_b": 1, "radius": 0.25},
    {"name": "A2 housing", "frame_a": 1, "p_a": [0, 0, -0.12], "frame_b": 1,
     "p_b": [0, 0, 0.12], "radius": 0.20},
    {"name": "upper arm", "frame_a": 1, "frame_b": 2, "radius": 0.15},
    {"name": "elbow", "frame_a": 2, "frame_b": 3, "radius": 0.15},
    {"name": "forearm", "frame_a": 3, "frame_b": 4, "radius": 0.12},
    {"name": "wrist", "frame_a": 4, "frame_b": 7, "radius": 0.09},
]  # fmt: skip
"""The catalogue KR 60-3's link capsules (``fabflow.robots.geometry``), written out."""


def kr60(geometry: str = "opw", **extra: Any) -> dict[str, Any]:
    """A ``robot.custom`` section with the KR 60-3's numbers (``geometry``: ``opw`` or ``dh``)."""
    spec: dict[str, Any] = {
        "name": "kr60_from_yaml",
        "vendor": "kuka",
        geometry: copy.deepcopy(KR60_OPW if geometry == "opw" else KR60_DH),
        "joint_limits_deg": [[-185, 185], [-135, 35], [-120, 158], [-350, 350], [-119, 119],
                             [-350, 350]],
        "joint_speeds_deg_s": [128, 102, 128, 260, 245, 322],
        "home_deg": [0, -90, 90, 0, 0, 0],
        "nominal_deg": [0, -90, 90, 0, 45, 0],
        "payload": 60.0,
        "reach": 2.203,
    }  # fmt: skip
    spec.update(extra)
    return spec


def project_text(custom: dict[str, Any] | None, **robot: Any) -> str:
    """A small project YAML whose robot is ``custom`` (or ``robot`` fields as given)."""
    section: dict[str, Any] = {"model": "custom", "custom": custom} if custom else {}
    section.update(robot)
    doc = {
        "name": "custom_robot",
        "robot": section,
        "elements": [{"cabin": {"origin": [0.0, 0.0, 0.0]}}],
    }
    return yaml.safe_dump(doc, sort_keys=False)


def cabin_with(custom: dict[str, Any], folder: Path) -> Path:
    """``projects/cabin`` with its robot replaced by ``custom`` (the rest as it is),
    written as ``folder/project.yaml``."""
    doc = yaml.safe_load((PROJECTS / "cabin" / "project.yaml").read_text(encoding="utf-8"))
    doc["robot"]["model"] = "custom"
    doc["robot"]["custom"] = custom
    path = folder / "project.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def _origin(T: np.ndarray) -> str:
    C, B, A = abc_from_matrix(T[:3, :3])[::-1]
    xyz = " ".join(repr(float(v)) for v in T[:3, 3])
    return f'<origin xyz="{xyz}" rpy="{float(C)!r} {float(B)!r} {float(A)!r}"/>'


def _rz(t: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]
    return T


def dh_urdf(name: str = "kuka_kr60_3") -> str:
    """A URDF of a catalogue DH arm: each joint at the previous DH link turned by its
    offset, its axis z or -z by the joint sign, a fixed ``flange`` link after the last.

    The base link is ``base``, the tip ``flange``; joint values are the controller's.
    """
    robot = get_robot(name)
    assert robot.dh is not None
    links = ["base", *[f"link_{i + 1}" for i in range(robot.dof)], "flange"]
    out = [f'<?xml version="1.0"?>\n<robot name="{name}">']
    out += [f'  <link name="{link}"/>' for link in links]
    before = np.eye(4)
    for i, (a, alpha, d, offset) in enumerate(robot.dh):
        lo, hi = robot.joint_limits[i]
        out.append(
            f'  <joint name="a{i + 1}" type="revolute">'
            f'<parent link="{links[i]}"/><child link="{links[i + 1]}"/>'
            f"{_origin(before @ _rz(offset))}"
            f'<axis xyz="0 0 {int(robot.joint_sign[i])}"/>'
            f'<limit lower="{float(lo)!r}" upper="{float(hi)!r}" effort="1000" '
            f'velocity="{float(robot.velocity_limits[i])!r}"/></joint>'
        )
        ca, sa = np.cos(alpha), np.sin(alpha)
        before = np.array([[1, 0, 0, a], [0, ca, -sa, 0], [0, sa, ca, d], [0, 0, 0, 1]])
    out.append(
        f'  <joint name="a{robot.dof}-flange" type="fixed"><parent link="{links[-2]}"/>'
        f'<child link="flange"/>{_origin(before @ robot.T_n_flange)}</joint>'
    )
    return "\n".join([*out, "</robot>", ""])


TRACK_URDF = """<?xml version="1.0"?>
<robot name="track_arm">
  <link name="floor"/><link name="carriage"/><link name="column"/><link name="boom"/>
  <link name="arm"/><link name="head"/><link name="tcp"/>
  <joint name="track" type="prismatic"><parent link="floor"/><child link="carriage"/>
    <origin xyz="0.5 0 0.2" rpy="0 0 0.4"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="6" effort="1" velocity="0.5"/></joint>
  <joint name="slew" type="revolute"><parent link="carriage"/><child link="column"/>
    <origin xyz="0 0 0.4" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1.0"/></joint>
  <joint name="lift" type="prismatic"><parent link="column"/><child link="boom"/>
    <origin xyz="0.1 0 0.3" rpy="0 0 0"/><axis xyz="0 0.6 0.8"/>
    <limit lower="0" upper="1.5" effort="1" velocity="0.3"/></joint>
  <joint name="shoulder" type="revolute"><parent link="boom"/><child link="arm"/>
    <origin xyz="0.2 0 0" rpy="0.3 -0.2 0.1"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1.0"/></joint>
  <joint name="wrist" type="revolute"><parent link="arm"/><child link="head"/>
    <origin xyz="0.8 0.05 0" rpy="0 0 0"/><axis xyz="1 1 0"/>
    <limit lower="-2.5" upper="2.5" effort="1" velocity="2.0"/></joint>
  <joint name="head-tcp" type="fixed"><parent link="head"/><child link="tcp"/>
    <origin xyz="0.1 0 -0.05" rpy="3.141592653589793 0 0"/></joint>
</robot>
"""
"""A linear track, slew, an inclined sliding boom and two revolute joints about
skewed axes: prismatic joints and general axes, ``floor`` to ``tcp``."""
