"""TODO: docstring."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree

from fabflow.design.elements import Element
from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.point_selection import (
    ClearanceRules,
    Workspace,
    avoid_obstacles,
    boxes_from_elements,
    clear_mask,
    optimal_points,
)
from fabflow.positioning.polar import (
    Instrument,
    make_instrument,
    polar_covariance,
    polar_to_cartesian,
    simulate_polar,
    to_world,
)
from fabflow.positioning.registration import register_points
from fabflow.positioning.result import BasePose
from fabflow.positioning.three_point import localize_three_point, three_point_base_points
from fabflow.positioning.total_station import (
    add_instrument_uncertainty,
    localize_observations,
    setup_covariance,
)
from fabflow.positioning.ts_io import read_observations, read_robot_points
from fabflow.project import Project, TotalStationSetup
from fabflow.robots import get_robot
from fabflow.transforms.se3 import apply_T, inv_T, make_T, perturb
from fabflow.transforms.so3 import matrix_from_abc

# ------------------------------------------------------------------ simulator


SAMPLE_TOLERANCE = 0.03
"""Largest distance (m) to a sampled prism position that counts as reachable (no closed-form IK)."""


@dataclass(frozen=True, eq=False)
class _Kinematics:
    """Reach test and forward kinematics of the prism for one robot and tool.

    Arms with closed-form IK reach a point with the tool pointing down (as in
    the reach maps). Machines without one (the 5-DOF BROKK) cannot choose the
    tool orientation, and a 360-degree prism does not need it: their reachable
    prism positions are a dense cloud of forward-kinematics samples of the
    joint space, and a point is reached by the nearest sample.
    """

    workspace: Workspace
    robot: Any
    T_flange_tool: np.ndarray
    samples_q: np.ndarray | None = None
    samples_tree: cKDTree | None = None

    def reachable(self, points: np.ndarray) -> np.ndarray:
        if self.samples_tree is not None:
            d, _ = self.samples_tree.query(points)
            return d <= SAMPLE_TOLERANCE
        T = self._tool_poses(points)
        _, valid = self.robot.ik_batch(T @ inv_T(self.T_flange_tool))
        return valid.any(axis=1)

    def _tool_poses(self, points: np.ndarray) -> np.ndarray:
        R_down = np.diag([1.0, -1.0, -1.0])
        return make_T(np.broadcast_to(R_down, (len(points), 3, 3)), points)

    def prism_points(self, points: np.ndarray) -> np.ndarray:
        """Joint values for the desired points, then the prism positions by FK."""
        if self.samples_tree is not None and self.samples_q is not None:
            d, k = self.samples_tree.query(points)
            bad = d > SAMPLE_TOLERANCE
            q = self.samples_q[k]
        else:
            T_base_flange = self._tool_poses(points) @ inv_T(self.T_flange_tool)
            q, valid = self.robot.ik_batch(T_base_flange)
            bad = ~valid.any(axis=1)
            q = q[np.arange(len(points)), np.argmax(valid, axis=1)]
        if bad.any():
            p = points[int(np.argmax(bad))]
            raise LocalizationError(
                f"{self.robot.name} cannot reach the localization point "
                f"({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f})"
            )
        return (self.robot.fk(q) @ self.T_flange_tool)[:, :3, 3]


@functools.lru_cache(maxsize=16)
def _joint_samples(model: str, T_flange_tool: tuple[float, ...]) -> tuple[np.ndarray, cKDTree]:

    robot = get_robot(model)
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    q = np.random.default_rng(0).uniform(lo, hi, (40000, robot.dof))
    p = (robot.fk(q) @ np.asarray(T_flange_tool).reshape(4, 4))[:, :3, 3]
    return q, cKDTree(p)


def _kinematics(model: str, T_flange_tool: np.ndarray, z_min: float) -> _Kinematics:
    """Workspace (reach sphere about the shoulder) with the robot's exact reach test."""

    robot = get_robot(model)
    shoulder = robot.frames(np.zeros(robot.dof))[1][:3, 3]
    ws = Workspace(center=(0.0, 0.0, float(shoulder[2])), reach=float(robot.reach), z_min=z_min)
    if robot.analytic_ik is None:
        q, tree = _joint_samples(model, tuple(np.asarray(T_flange_tool, float).ravel()))
        kin = _Kinematics(ws, robot, T_flange_tool, q, tree)
    else:
        kin = _Kinematics(ws, robot, T_flange_tool)
    # the top of the reach sphere is out of reach with the tool held down: cap the
    # workspace at the highest reachable point (in front of the robot, 5 cm margin)
    x = np.arange(0.1, ws.radius, 0.05)
    z = np.arange(z_min, ws.center[2] + ws.radius, 0.05)
    grid = np.stack(np.meshgrid(x, [0.0], z, indexing="ij"), axis=-1).reshape(-1, 3)
    ok = kin.reachable(grid)
    if not ok.any():
        raise LocalizationError(f"{model}: no prism position above z = {z_min} m is reachable")
    z_max = float(grid[ok, 2].max()) - 0.05
    return replace(kin, workspace=replace(ws, reachable=kin.reachable, z_max=z_max))


@functools.lru_cache(maxsize=64)
def _cached_optimal_points(n: int, workspace: Workspace) -> np.ndarray:
    # a fixed seed: the same workspace always gets the same points
    return optimal_points(n, replace(workspace, reachable=None), np.random.default_rng(0))


def instrument_for(setup: TotalStationSetup) -> Instrument:
    """The accuracy model of a project's total station setup."""
    return make_instrument(
        setup.instrument, setup.distance_sigma_mm, setup.distance_ppm, setup.angle_sigma_arcsec
    )


def localize_station(
    project: Project,
    T_world_base: np.ndarray,
    rng: np.random.Generator,
    station_id: str | None = None,
    built: Sequence[Element] = (),
) -> BasePose:
    """Simulate a total station localization of the robot base at one station.

    When the project's setup names measured ``observations`` and
    ``robot_points`` files, those are used instead (:func:`localize_files`)
    and ``T_world_base``, ``rng`` and ``built`` are not.

    The prism points are chosen in the base frame (eqs 9-11 for the
    ``arbitrary`` procedure, then moved clear of ``built`` and of the line of
    sight; ``P1, P1 + d x, P1 + d y`` for ``three_point``), reached by
    inverse kinematics and placed by forward kinematics of the project's robot.
    The true prism positions (plus the robot's repeatability noise) are
    observed from ``T_world_instrument`` with the instrument's noise, and the
    base pose is estimated from the readings.

    Parameters
    ----------
    project
        The project (``localization.total_station``, ``robot``, ``simulation``).
    T_world_base
        True 4x4 pose of the robot base in the world (metres).
    rng
        Source of all noise.
    station_id
        Stored in the result.
    built
        Elements already built (obstacles for the prism, the arm and the line of sight).

    Returns
    -------
    BasePose
        Estimated pose with covariance, residuals and quality figures.
    """
    setup = project.localization.total_station or TotalStationSetup()
    if setup.observations is not None and setup.robot_points is not None:
        # measured readings were supplied: localize from them, nothing is simulated
        return localize_files(
            setup.observations,
            setup.robot_points,
            project=project,
            robot_sigma=project.simulation.robot_repeatability,
            station=station_id,
        )
    instrument = instrument_for(setup)
    T_world_instrument = setup.T_world_instrument.matrix()
    T_world_instrument[:3, 3] += T_world_instrument[:3, 2] * setup.instrument_height
    T_world_base = np.asarray(T_world_base, dtype=float)
    T_base_world = inv_T(T_world_base)
    T_flange_tool = project.robot.tool.T_flange_tool.matrix()
    kin = _kinematics(project.robot.model, T_flange_tool, setup.z_min)
    ws = kin.workspace
    boxes = boxes_from_elements(built, T_world_base)
    rules = ClearanceRules(
        tool_half_extents=setup.tool_half_extents,
        sight_from=tuple(float(v) for v in apply_T(T_base_world, T_world_instrument[:3, 3])),
    )
    moved = np.zeros(0)
    dropped: tuple[tuple[int, str], ...] = ()
    if setup.procedure == "three_point":
        d = setup.three_point_step
        c = np.asarray(ws.center)
        p1 = c + np.array([0.55 * ws.radius - 0.5 * d, -0.5 * d, 0.0])
        P_des = three_point_base_points(p1, d)
        ok = clear_mask(P_des, ws, boxes, rules)
        if not ok.all():
            raise LocalizationError(
                f"station {station_id}: three-point localization point P{int(np.argmin(ok)) + 1} "
                "is blocked or out of reach; use procedure 'arbitrary'"
            )
    else:
        clear = avoid_obstacles(
            _cached_optimal_points(setup.n_points, ws), ws, boxes, rules, min_points=3
        )
        P_des, moved, dropped = clear.points, clear.moved, clear.dropped
    P_base = kin.prism_points(P_des)
    sigma_robot = project.simulation.robot_repeatability
    P_true = P_base + rng.normal(0.0, 1.0, P_base.shape) * sigma_robot
    # the instrument really stands where its (uncertain) set-up puts it, off by a draw
    C_setup = setup_covariance(setup)
    T_world_instrument_true = perturb(
        T_world_instrument, rng.normal(0.0, 1.0, 6) * np.sqrt(np.diag(C_setup))
    )
    p_instr = apply_T(inv_T(T_world_instrument_true), apply_T(T_world_base, P_true))
    hz, v, sd = simulate_polar(p_instr, instrument, rng)
    M, C = to_world(
        T_world_instrument, polar_to_cartesian(hz, v, sd), polar_covariance(hz, v, sd, instrument)
    )
    assert C is not None
    if setup.procedure == "three_point":
        reg = localize_three_point(M, P_base[0], setup.three_point_step, C, sigma_robot)
    else:
        reg = register_points(
            P_base, M, point_cov=C, base_sigma=sigma_robot, reject_outlier=len(P_base) >= 5
        )
    reg = add_instrument_uncertainty(reg, T_world_instrument, C_setup)
    quality = {
        "procedure": setup.procedure,
        "instrument": instrument.name,
        "points_base": P_base.tolist(),
        "points_world": M.tolist(),
        "slope_distances": sd.tolist(),
        "moved_for_obstacles": moved.tolist(),
        "dropped_points": [why for _, why in dropped],
    }
    return reg.to_base_pose(station=station_id, quality=quality)


def prism_points_from_joints(
    model: str,
    joints: np.ndarray,
    T_flange_prism: np.ndarray,
    source: str | None = None,
    lines: Sequence[int] = (),
) -> np.ndarray:
    """Prism positions ``(n, 3)`` in the base frame from joint values ``(n, dof)`` (radians).

    Raises
    ------
    InputError
        When the number of joints does not match the robot or a configuration
        lies outside the joint limits (the robot cannot have stood there).
    """

    rob = get_robot(model)
    q = np.asarray(joints, dtype=float)
    if q.shape[1] != rob.dof:
        raise InputError(
            f"{model} has {rob.dof} joints but the file gives {q.shape[1]} (q1_deg..)", source
        )
    ok = rob.within_limits(q)
    if not ok.all():
        k = int(np.argmin(ok))
        where = f"line {lines[k]}" if lines else None
        raise InputError(f"joint values outside the limits of {model}", source, where)
    return (rob.fk(q) @ np.asarray(T_flange_prism, dtype=float))[:, :3, 3]


def _triple(text: str | None, name: str, default: tuple[float, float, float]) -> np.ndarray:
    if text is None:
        return np.asarray(default, dtype=float)
    try:
        values = [float(v) for v in text.replace(";", ",").split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(np.isfinite(values)):
        raise InputError(f"{name} must be three numbers 'a,b,c', got {text!r}")
    return np.asarray(values, dtype=float)


def localize_files(
    observations_path: str | Path,
    robot_points_path: str | Path,
    *,
    project: Project | None = None,
    instrument: str | None = None,
    distance_sigma_mm: float | None = None,
    distance_ppm: float | None = None,
    angle_sigma_arcsec: float | None = None,
    instrument_xyz: str | None = None,
    instrument_abc_deg: str | None = None,
    instrument_height: float | None = None,
    robot_sigma: float = 0.0,
    method: Literal["closed_form", "optimize"] = "closed_form",
    reject_outlier: bool = True,
    station: str | None = None,
    robot: str | None = None,
    tcp_xyz: str | None = None,
) -> BasePose:
    """Localize from an observation file and a robot point file (CLI ``localize total-station``).

    The instrument and its pose come from the project's
    ``localization.total_station`` section when ``project`` is given, else from
    the defaults (Leica MS50, instrument frame = world); the keyword arguments
    override either. Pose strings are ``"x,y,z"`` (metres) and ``"A,B,C"``
    (degrees, R = Rz(A) Ry(B) Rx(C)). A robot point file of joint values is
    turned into prism positions by forward kinematics of ``robot`` (else the
    project's robot) with the prism at the project's TCP, or at ``tcp_xyz``
    (metres, flange frame).
    """
    setup = TotalStationSetup()
    if project is not None and project.localization.total_station is not None:
        setup = project.localization.total_station
    T0 = setup.T_world_instrument if project is not None else None
    inst = make_instrument(
        instrument or setup.instrument,
        distance_sigma_mm if distance_sigma_mm is not None else setup.distance_sigma_mm,
        distance_ppm if distance_ppm is not None else setup.distance_ppm,
        angle_sigma_arcsec if angle_sigma_arcsec is not None else setup.angle_sigma_arcsec,
    )
    xyz = _triple(instrument_xyz, "--instrument-xyz", T0.xyz if T0 else (0.0, 0.0, 0.0))
    abc = _triple(instrument_abc_deg, "--instrument-abc-deg", T0.abc_deg if T0 else (0.0, 0.0, 0.0))
    T_world_instrument = make_T(matrix_from_abc(*np.radians(abc)), xyz)
    hi = setup.instrument_height if instrument_height is None else instrument_height
    T_world_instrument[:3, 3] += T_world_instrument[:3, 2] * hi
    obs = read_observations(observations_path)
    rp = read_robot_points(robot_points_path)
    if rp.xyz is not None:
        pts = rp.xyz
    else:
        assert rp.joints is not None
        model = robot or (project.robot.model if project is not None else None)
        if model is None:
            raise InputError(
                "the robot point file holds joint values; name the robot (--robot or --project)",
                rp.source,
            )
        T_flange_tool = (
            project.robot.tool.T_flange_tool.matrix() if project is not None else np.eye(4)
        )
        if tcp_xyz is not None:
            T_flange_tool = make_T(T_flange_tool[:3, :3], _triple(tcp_xyz, "--tcp-xyz", (0, 0, 0)))
        pts = prism_points_from_joints(model, rp.joints, T_flange_tool, rp.source, rp.lines)
    reg, matched = localize_observations(
        obs, rp.point_ids, pts, inst, T_world_instrument, robot_sigma, method, reject_outlier
    )
    if project is not None:
        reg = add_instrument_uncertainty(reg, T_world_instrument, setup_covariance(setup))
    quality = {
        "instrument": inst.name,
        "point_ids": list(matched),
        "observations": str(observations_path),
        "robot_points": str(robot_points_path),
        "T_world_instrument": T_world_instrument.tolist(),
    }
    return reg.to_base_pose(station=station, quality=quality)
