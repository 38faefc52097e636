"""Synthetic designs, plans and a stand-in arm, for tests, benchmarks and demos."""

from __future__ import annotations

import numpy as np

from fabflow.design.elements import Element
from fabflow.tasks.plan import Plan, Station, WorkPackage


def translation(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    """4x4 pose: rotation ``yaw`` (radians) about z, then translation (metres)."""
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x, y, z)
    return T


class PointArm:
    """A stand-in arm: q is the flange position in the base frame.

    It is drawn through the foot of axis 1, a shoulder 0.8 m above it and the
    flange; ``ik`` returns the flange position, or nothing beyond ``reach``.
    """

    name = "point_arm"

    def __init__(self, reach: float = 3.0) -> None:
        self.reach = reach
        self.home = np.array([0.5, 0.0, 1.0])

    def joint_origins(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        foot = np.zeros_like(q)
        shoulder = np.zeros_like(q)
        shoulder[..., 2] = 0.8
        return np.stack([foot, shoulder, q], axis=-2)

    def fk(self, q: np.ndarray) -> np.ndarray:
        T = np.eye(4)
        T[:3, 3] = q
        return T

    def ik(self, T_base_flange: np.ndarray) -> list[np.ndarray]:
        p = np.asarray(T_base_flange, dtype=float)[:3, 3]
        return [p.copy()] if np.linalg.norm(p) <= self.reach else []


def wall_design(
    n_rows: int = 3, n_per_row: int = 4, n_stations: int = 2, n_prebuilt: int = 2
) -> tuple[list[Element], Plan]:
    """A straight wall of blocks along x, a print path and a task point.

    The first ``n_prebuilt`` blocks are pre-built (not in the plan); the rest,
    the print path and the task point are split over ``n_stations`` stations in
    row order. Targets are the element poses, gripper pointing down.
    """
    ext = np.array([0.6, 0.105, 0.105])
    elements: list[Element] = []
    for r in range(n_rows):
        for i in range(n_per_row):
            T = translation(0.6 * i + 0.3 * (r % 2), 0.0, 0.0525 + 0.105 * r)
            elements.append(
                Element(
                    id=f"B{r:02d}{i:02d}",
                    type="block",
                    T_world_element=T,
                    layer=r,
                    extents=ext,
                    robot_built=len(elements) >= n_prebuilt,
                )
            )
    elements.append(
        Element(
            id="P0",
            type="print_path",
            T_world_element=translation(0.0, 1.0, 0.0),
            layer=n_rows,
            polyline=np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.5, 0.0]]),
            attributes={"bead_width": 0.03},
        )
    )
    elements.append(
        Element(id="T0", type="task_point", T_world_element=translation(1.0, -1.0, 0.5))
    )
    planned = [e for e in elements if e.robot_built]
    chunks = np.array_split(np.arange(len(planned)), n_stations)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    packages = []
    for s, chunk in enumerate(chunks):
        station = Station(id=f"S{s + 1}", T_world_platform=translation(0.8 * s, -1.6, 0.0, 0.3 * s))
        packages.append(
            WorkPackage(
                index=s,
                station=station,
                elements=tuple(planned[i].id for i in chunk),
                T_world_targets=np.array([planned[i].T_world_element @ flip for i in chunk]),
                travel=0.0 if s == 0 else 0.8,
            )
        )
    return elements, Plan(work_packages=tuple(packages))


def rows_of_walls(n_walls: int) -> tuple[list[Element], Plan]:
    """``n_walls`` copies of a 737-block-sized wall design side by side (benchmark scale)."""
    elements: list[Element] = []
    packages: list[WorkPackage] = []
    for w in range(n_walls):
        els, plan = wall_design(n_rows=30, n_per_row=24, n_stations=3, n_prebuilt=200)
        shift = translation(0.0, 6.0 * w, 0.0)
        for e in els:
            elements.append(
                Element(
                    id=f"W{w}_{e.id}",
                    type=e.type,
                    T_world_element=shift @ e.T_world_element,
                    layer=e.layer,
                    extents=e.extents,
                    polyline=e.polyline,
                    robot_built=e.robot_built,
                    attributes=e.attributes,
                )
            )
        for wp in plan.work_packages:
            st = wp.station
            packages.append(
                WorkPackage(
                    index=len(packages),
                    station=Station(
                        id=f"W{w}_{st.id}", T_world_platform=shift @ st.T_world_platform
                    ),
                    elements=tuple(f"W{w}_{eid}" for eid in wp.elements),
                    T_world_targets=shift @ wp.T_world_targets,
                )
            )
    return elements, Plan(work_packages=tuple(packages))
