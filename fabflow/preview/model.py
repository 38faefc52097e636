"""What the preview shows, as plain numpy arrays, independent of viser.

A :class:`PreviewModel` is built once from the elements, the plan and the robot
(:func:`build_model`); the scene (:mod:`fabflow.preview.scene`) only reads it.
Steps are counted in placed elements: step ``k`` (``0 <= k <= n_steps``) shows
the first ``k`` elements of the build sequence; the element being placed at
step ``k >= 1`` is ``sequence[k - 1]``, the platform stands at that element's
station and the arm reaches its target. Step 0 shows the platform at the first
station with the arm in its home configuration.

Elements that are not in the plan (pre-built parts, ``robot_built=False``) are
shown from step 0 on. Every pose is in the world frame, metres.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from fabflow.design.elements import Element
from fabflow.errors import InputError
from fabflow.positioning.result import BasePose
from fabflow.preview.arm import ArmModel, arm_track
from fabflow.project import Platform
from fabflow.tasks.plan import Plan
from fabflow.transforms.so3 import quat_from_matrix

ColourMode = Literal["station", "state", "layer", "deviation"]
COLOUR_MODES: tuple[str, ...] = ("station", "state", "layer", "deviation")
"""Block colour modes: by station, by build state, by layer, by simulated deviation."""

# Tableau 10: distinct, colour-blind friendly hues for stations.
STATION_PALETTE = np.array(
    [
        [78, 121, 167],
        [242, 142, 43],
        [89, 161, 79],
        [225, 87, 89],
        [118, 183, 178],
        [237, 201, 72],
        [176, 122, 161],
        [255, 157, 167],
        [156, 117, 95],
        [186, 176, 172],
    ],
    dtype=np.uint8,
)
STATION_COLOUR_NAMES = (
    "blue",
    "orange",
    "green",
    "red",
    "teal",
    "yellow",
    "purple",
    "pink",
    "brown",
    "grey",
)
"""Names of the :data:`STATION_PALETTE` colours, for text legends."""
PREBUILT_COLOUR = np.array([150, 150, 150], dtype=np.uint8)
"""Elements not placed by the robot (not in the plan)."""
STATE_COLOURS: dict[str, np.ndarray] = {
    "built earlier": np.array([181, 140, 94], dtype=np.uint8),
    "built at this visit": np.array([232, 196, 128], dtype=np.uint8),
    "being placed": np.array([230, 60, 40], dtype=np.uint8),
    "pre-built": PREBUILT_COLOUR,
}
UNKNOWN_DEVIATION_COLOUR = np.array([200, 200, 200], dtype=np.uint8)


@dataclass(frozen=True, eq=False)
class PreviewModel:
    """Everything the scene draws, precomputed (world frame, metres).

    Attributes
    ----------
    name
        Project name (the page title).
    elements
        All elements of the design.
    built_at
        (E,) step at which each element appears: 1..n_steps for planned
        elements, 0 for elements not in the plan (always shown).
    sequence
        (S,) element indices in build order.
    step_package
        (S,) work-package index of each step.
    package_station
        (P,) index into ``station_ids`` of each work package.
    station_ids
        Distinct station ids in order of first visit.
    T_world_platform
        (P, 4, 4) platform pose of each work package.
    lift
        (P,) lift height of each work package (metres).
    T_world_base
        (P, 4, 4) planned arm base pose of each work package.
    T_world_targets
        (S, 4, 4) tool target of each step.
    travel
        (P,) platform travel to each work package (metres).
    block_index
        (B,) indices of the block elements.
    block_positions, block_wxyz, block_extents
        (B, 3), (B, 4), (B, 3) block centres, orientations (w, x, y, z) and sizes.
    path_index
        (Q,) indices of the print-path elements.
    path_points
        One (M, 3) world polyline per print path.
    point_index
        (T,) indices of the task-point elements.
    point_positions, point_wxyz
        (T, 3), (T, 4) task-point frames.
    arm
        The arm model, or ``None`` when no kinematic model is available.
    arm_points
        (S + 1, n_points, 3) arm drawing points in the world at each step
        (empty when ``arm`` is ``None``).
    arm_reached
        (S + 1,) whether the arm reaches the step's target (step 0: home).
    arm_q
        (S + 1, dof) joint configuration drawn at each step (radians).
    T_world_tool
        (S + 1, 4, 4) tool pose drawn at each step.
    platform
        Footprint, lift range, arm mounting and safety margin.
    deviation
        (E,) simulated deviation of each element (metres), NaN where unknown,
        or ``None`` when no simulation result was given.
    tolerance
        Position tolerance of the project (metres), the deviation colour scale.
    localization
        Localization results keyed by work-package index (one per visit) or by
        station id (one per station); see :meth:`localization_at`.
    method
        The project's localization method.
    """

    name: str
    elements: tuple[Element, ...]
    built_at: np.ndarray
    sequence: np.ndarray
    step_package: np.ndarray
    package_station: np.ndarray
    station_ids: tuple[str, ...]
    T_world_platform: np.ndarray
    lift: np.ndarray
    T_world_base: np.ndarray
    T_world_targets: np.ndarray
    travel: np.ndarray
    block_index: np.ndarray
    block_positions: np.ndarray
    block_wxyz: np.ndarray
    block_extents: np.ndarray
    path_index: np.ndarray
    path_points: tuple[np.ndarray, ...]
    point_index: np.ndarray
    point_positions: np.ndarray
    point_wxyz: np.ndarray
    arm: ArmModel | None
    arm_points: np.ndarray
    arm_reached: np.ndarray
    arm_q: np.ndarray
    T_world_tool: np.ndarray
    platform: Platform
    deviation: np.ndarray | None = None
    tolerance: float = 0.01
    localization: Mapping[int | str, BasePose] = field(default_factory=dict)
    method: str = "total_station"

    @property
    def n_steps(self) -> int:
        """Number of build steps (elements in the plan)."""
        return int(self.sequence.shape[0])

    def package_at(self, step: int) -> int:
        """Work-package index shown at ``step`` (the first package at step 0)."""
        step = self.check_step(step)
        if self.step_package.size == 0:
            return -1
        return int(self.step_package[max(step, 1) - 1])

    def station_at(self, step: int) -> str | None:
        """Station id at ``step``, or ``None`` for a plan without work packages."""
        p = self.package_at(step)
        return None if p < 0 else self.station_ids[int(self.package_station[p])]

    def element_at(self, step: int) -> Element | None:
        """The element placed at ``step`` (``None`` at step 0)."""
        step = self.check_step(step)
        return None if step == 0 else self.elements[int(self.sequence[step - 1])]

    def localization_at(self, package: int) -> BasePose | None:
        """The localization result of a work package (by its index, else its station id)."""
        if package < 0:
            return None
        result = self.localization.get(package)
        if result is None:
            result = self.localization.get(self.station_ids[int(self.package_station[package])])
        return result

    def check_step(self, step: int) -> int:
        """Return ``step`` as an int, or raise :class:`InputError` if outside 0..n_steps."""
        step = int(step)
        if not 0 <= step <= self.n_steps:
            raise InputError(f"step must be between 0 and {self.n_steps}, got {step}")
        return step

    def visible(self, step: int) -> np.ndarray:
        """(E,) mask of the elements that exist after ``step`` placements."""
        return self.built_at <= self.check_step(step)

    def first_step_of_station(self, station_id: str) -> int:
        """First step (1-based) of the first visit to a station."""
        if station_id not in self.station_ids:
            raise InputError(f"unknown station '{station_id}'; the plan has {self.station_ids}")
        s = self.station_ids.index(station_id)
        steps = np.flatnonzero(self.package_station[self.step_package] == s)
        return int(steps[0]) + 1 if steps.size else 0

    def colour_modes(self) -> tuple[str, ...]:
        """The colour modes this model supports (deviation only with a simulation)."""
        return COLOUR_MODES if self.deviation is not None else COLOUR_MODES[:3]

    def element_colours(self, mode: str, step: int) -> np.ndarray:
        """(E, 3) uint8 colours of every element for a colour mode at a step.

        Raises
        ------
        InputError
            For an unknown mode, or ``"deviation"`` without simulation results.
        """
        step = self.check_step(step)
        E = len(self.elements)
        planned = self.built_at > 0
        out = np.empty((E, 3), dtype=np.uint8)
        out[:] = PREBUILT_COLOUR
        if mode == "station":
            stations = self.package_station[self.step_package]
            out[self.sequence] = STATION_PALETTE[stations % len(STATION_PALETTE)]
        elif mode == "state":
            current = self.package_at(step)
            pkg = np.full(E, -1)
            pkg[self.sequence] = self.step_package
            out[planned] = STATE_COLOURS["built earlier"]
            out[planned & (pkg == current)] = STATE_COLOURS["built at this visit"]
            if step > 0:
                out[self.sequence[step - 1]] = STATE_COLOURS["being placed"]
        elif mode == "layer":
            layers = np.array([e.layer for e in self.elements], dtype=float)
            lowest = float(layers.min()) if E else 0.0
            span = max(float(layers.max()) - lowest if E else 0.0, 1.0)
            out[:] = _colormap("viridis", (layers - lowest) / span)
        elif mode == "deviation":
            if self.deviation is None:
                raise InputError(
                    "colour mode 'deviation' needs simulation results (pass --sim DIR)"
                )
            known = np.isfinite(self.deviation)
            out[:] = UNKNOWN_DEVIATION_COLOUR
            scaled = np.clip(self.deviation[known] / (2.0 * self.tolerance), 0.0, 1.0)
            out[known] = _colormap("RdYlGn_r", scaled)
        else:
            raise InputError(f"unknown colour mode '{mode}'; expected one of {COLOUR_MODES}")
        return out

    def legend_text(self, mode: str) -> str:
        """A one-line legend naming the colours, for the exported file (no control panel)."""
        if mode == "station":
            names = ", ".join(
                f"{sid} {STATION_COLOUR_NAMES[i % len(STATION_COLOUR_NAMES)]}"
                for i, sid in enumerate(self.station_ids)
            )
            return f"colour by station: {names}; pre-built grey"
        if mode == "state":
            return (
                "colour by build state: red being placed, light wood built at this visit, "
                "dark wood built earlier, grey pre-built"
            )
        if mode == "layer":
            return "colour by layer: purple lowest to yellow highest"
        if mode == "deviation":
            tol = 1000 * self.tolerance
            return (
                f"colour by simulated deviation: green 0 mm, yellow {tol:.0f} mm (tolerance), "
                f"red {2 * tol:.0f} mm and more; light grey not simulated"
            )
        raise InputError(f"unknown colour mode '{mode}'; expected one of {COLOUR_MODES}")

    def legend(self, mode: str) -> list[tuple[str, tuple[int, int, int]]]:
        """Legend entries ``(label, rgb)`` for a colour mode."""
        if mode == "station":
            rows = [
                (sid, STATION_PALETTE[i % len(STATION_PALETTE)])
                for i, sid in enumerate(self.station_ids)
            ]
            rows.append(("pre-built", PREBUILT_COLOUR))
        elif mode == "state":
            rows = list(STATE_COLOURS.items())
        elif mode == "layer":
            layers = [e.layer for e in self.elements] or [0]
            lo, hi = min(layers), max(layers)
            rows = [
                (f"layer {lo + round(f * (hi - lo))}", _colormap("viridis", np.array([f]))[0])
                for f in (0.0, 0.5, 1.0)
            ]
        elif mode == "deviation":
            tol = self.tolerance
            rows = [
                (f"{1000 * f * 2 * tol:.1f} mm", _colormap("RdYlGn_r", np.array([f]))[0])
                for f in (0.0, 0.25, 0.5, 0.75, 1.0)
            ]
            rows[2] = (rows[2][0] + " (tolerance)", rows[2][1])
            rows[-1] = ("≥ " + rows[-1][0], rows[-1][1])
            rows.append(("not simulated", UNKNOWN_DEVIATION_COLOUR))
        else:
            raise InputError(f"unknown colour mode '{mode}'; expected one of {COLOUR_MODES}")
        return [(label, tuple(int(c) for c in rgb)) for label, rgb in rows]  # type: ignore[misc]


def _colormap(name: str, values: np.ndarray) -> np.ndarray:
    """Map values in [0, 1] to uint8 RGB with a matplotlib colour map."""
    from matplotlib import colormaps

    rgba = colormaps[name](np.asarray(values, dtype=float))
    return np.round(np.asarray(rgba)[..., :3] * 255).astype(np.uint8)


def build_model(
    elements: Sequence[Element],
    plan: Plan,
    *,
    name: str = "fabflow",
    platform: Platform | None = None,
    T_flange_tool: np.ndarray | None = None,
    arm: ArmModel | None = None,
    deviation: Mapping[str, float] | None = None,
    tolerance: float = 0.01,
    localization: Mapping[int | str, BasePose] | None = None,
    method: str = "total_station",
) -> PreviewModel:
    """Precompute everything the preview draws.

    Parameters
    ----------
    elements
        The design's elements (world frame).
    plan
        Work packages in execution order; their element ids must exist in ``elements``.
    name
        Project name.
    platform
        Platform geometry (footprint, lift, ``T_platform_base``); the project default if ``None``.
    T_flange_tool
        4x4 tool centre point in the flange frame (identity if ``None``).
    arm
        Kinematic model for drawing the arm; no arm is drawn when ``None``.
    deviation
        Simulated deviation (metres) by element id.
    tolerance
        Position tolerance (metres); the deviation colour scale runs to twice this.
    localization
        Localization results by work-package index or station id.
    method
        The project's localization method, shown in the info panel.

    Raises
    ------
    InputError
        When the plan names an element that is not in ``elements`` or places one twice.
    """
    platform = platform or Platform()
    T_flange_tool = np.eye(4) if T_flange_tool is None else np.asarray(T_flange_tool, float)
    elements = tuple(elements)
    sequence, step_package, built_at = _build_sequence(elements, plan)

    station_ids = tuple(s.id for s in plan.stations)
    package_station = np.array(
        [station_ids.index(wp.station.id) for wp in plan.work_packages], dtype=np.int64
    )
    P = len(plan.work_packages)
    T_platform_base = platform.T_platform_base.matrix()
    T_world_platform = np.array(
        [wp.station.T_world_platform for wp in plan.work_packages], dtype=float
    ).reshape(P, 4, 4)
    lift = np.array([wp.station.lift for wp in plan.work_packages], dtype=float)
    T_wb = np.array(
        [wp.station.T_world_base(T_platform_base) for wp in plan.work_packages], dtype=float
    ).reshape(P, 4, 4)
    targets = [np.asarray(wp.T_world_targets, dtype=float) for wp in plan.work_packages]
    for wp, t in zip(plan.work_packages, targets, strict=True):
        if t.shape != (len(wp.elements), 4, 4):
            raise InputError(
                f"work package {wp.index}: {len(wp.elements)} elements but "
                f"T_world_targets of shape {t.shape}"
            )
    T_world_targets = np.concatenate(targets) if targets else np.zeros((0, 4, 4))

    types = np.array([e.type for e in elements])
    block_index = np.flatnonzero(types == "block")
    poses = (
        np.stack([elements[i].T_world_element for i in block_index])
        if block_index.size
        else np.zeros((0, 4, 4))
    )
    extents = np.array(
        [
            elements[i].extents if elements[i].extents is not None else (0.1, 0.1, 0.1)
            for i in block_index
        ],
        dtype=float,
    ).reshape(-1, 3)

    path_index = np.flatnonzero(types == "print_path")
    path_points = tuple(_path_world(elements[i]) for i in path_index)
    point_index = np.flatnonzero(types == "task_point")
    point_T = (
        np.stack([elements[i].T_world_element for i in point_index])
        if point_index.size
        else np.zeros((0, 4, 4))
    )

    arm_q, reached, arm_points, T_world_tool = arm_track(
        arm, T_wb, step_package, T_world_targets, T_flange_tool
    )

    dev = None
    if deviation is not None:
        dev = np.array([deviation.get(e.id, np.nan) for e in elements], dtype=float)

    return PreviewModel(
        name=name,
        elements=elements,
        built_at=built_at,
        sequence=sequence,
        step_package=step_package,
        package_station=package_station,
        station_ids=station_ids,
        T_world_platform=T_world_platform,
        lift=lift,
        T_world_base=T_wb,
        T_world_targets=T_world_targets,
        travel=np.array([wp.travel for wp in plan.work_packages], dtype=float),
        block_index=block_index,
        block_positions=poses[:, :3, 3].astype(np.float32),
        block_wxyz=quat_from_matrix(poses[:, :3, :3]).astype(np.float32).reshape(-1, 4),
        block_extents=extents.astype(np.float32),
        path_index=path_index,
        path_points=path_points,
        point_index=point_index,
        point_positions=point_T[:, :3, 3].astype(np.float32),
        point_wxyz=quat_from_matrix(point_T[:, :3, :3]).astype(np.float32).reshape(-1, 4),
        arm=arm,
        arm_points=arm_points,
        arm_reached=reached,
        arm_q=arm_q,
        T_world_tool=T_world_tool,
        platform=platform,
        deviation=dev,
        tolerance=float(tolerance),
        localization=dict(localization or {}),
        method=method,
    )


def _build_sequence(
    elements: Sequence[Element], plan: Plan
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The build order as element indices, its work package per step, and the step of each element.

    Returns
    -------
    sequence
        (S,) element indices in build order.
    step_package
        (S,) work package index of every step.
    built_at
        (N,) 1-based step at which each element is built (0: never, pre-built).

    Raises
    ------
    InputError
        When the element ids are not unique, or the plan names an element that is
        not in ``elements`` or places one twice.
    """
    index_of = {e.id: i for i, e in enumerate(elements)}
    if len(index_of) != len(elements):
        raise InputError("element ids are not unique")
    seq_ids = [eid for wp in plan.work_packages for eid in wp.elements]
    missing = [eid for eid in seq_ids if eid not in index_of]
    if missing:
        raise InputError(f"the plan names elements that the design does not have: {missing[:10]}")
    sequence = np.array([index_of[eid] for eid in seq_ids], dtype=np.int64)
    if np.unique(sequence).size != sequence.size:
        raise InputError("the plan places some elements more than once")
    step_package = np.repeat(
        np.arange(len(plan.work_packages)), [len(wp.elements) for wp in plan.work_packages]
    ).astype(np.int64)
    built_at = np.zeros(len(elements), dtype=np.int64)
    built_at[sequence] = np.arange(1, sequence.size + 1)
    return sequence, step_package, built_at


def _path_world(element: Element) -> np.ndarray:
    """A print path's polyline in the world frame, (M, 3)."""
    pts = np.asarray(element.polyline if element.polyline is not None else np.zeros((0, 3)))
    T = np.asarray(element.T_world_element, dtype=float)
    return (pts @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
