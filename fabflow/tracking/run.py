"""One tracked print on the simulated machine: the 100 Hz loop of paper 000.

Every 10 ms: the hydraulic joints move (:class:`~fabflow.robots.hydraulic.ValveJoints`,
the machine as built: :func:`~fabflow.sensors.excavator.true_arm`), the
machine reads its joints and base (:class:`~fabflow.sensors.excavator.ExcavatorSensors`),
the kinematics (nominal model on those readings) step the EKF, every tenth
step the LiDAR scans and its ICP pose is queued to reach the filter one latency
later, at its own timestamp; the controller sets the valves from the fused
estimate (closed loop) or from the joint sensors alone (open loop).

The machine holds the path's start for ``tracking.settle_s`` seconds before it
prints; errors are counted over the print only.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from fabflow.design.generate import generate_elements
from fabflow.errors import InputError
from fabflow.positioning.icp_fusion import FusionParams, IcpKinematicsFilter
from fabflow.project import Project
from fabflow.robots.catalog import get_robot, vendor_of
from fabflow.robots.chain import RobotModel
from fabflow.robots.hydraulic import HydraulicJoints, ValveJoints
from fabflow.sensors.excavator import NO_ERRORS, ExcavatorErrors, ExcavatorSensors, true_arm
from fabflow.sensors.site_map import simulated_site_map
from fabflow.sensors.site_scene import site_scene
from fabflow.tasks.planner import plan_project
from fabflow.tracking.controller import TrackingController, TrackingGains, feed_forward
from fabflow.tracking.lidar import IcpFix, lidar_fix
from fabflow.tracking.reference import R_DOWN, Reference, print_reference
from fabflow.transforms.se3 import perturb

FloatArray = NDArray[np.float64]

Mode = Literal["closed", "open"]

RATE_HZ = 100.0
"""The loop's rate (paper 000: kinematics and reference at 100 Hz)."""

ICP_EVERY = 10
"""Loop steps per LiDAR revolution (10 Hz)."""


@dataclass(frozen=True, eq=False)
class TrackingRun:
    """What one tracked print did (world frame, metres, seconds).

    Attributes
    ----------
    mode
        ``"closed"`` (feedback on the fused estimate) or ``"open"`` (joint sensors only).
    t
        ``(S,)`` times of the print's samples (the settling before it left out).
    p_ref, p_true, p_est, p_kin, p_icp
        ``(S, 3)`` nozzle positions: the reference, the truth, the fused estimate,
        the kinematics alone and the last ICP fix held (NaN before the first).
    icp_error
        ``(F, 3)`` error of each ICP fix of the print against the truth at its
        scan's time (empty in open loop).
    counts
        ICP fixes made, applied, gated, too old and failed.
    mean_nis
        Mean normalized innovation squared of the applied ICP fixes (6 when consistent).
    simulated_s
        Machine time the loop simulated (s; the settling included).
    wall_s
        Wall-clock time of the loop (s).
    """

    mode: Mode
    t: FloatArray
    p_ref: FloatArray
    p_true: FloatArray
    p_est: FloatArray
    p_kin: FloatArray
    p_icp: FloatArray
    icp_error: FloatArray
    counts: dict[str, int]
    mean_nis: float
    simulated_s: float
    wall_s: float


def track_print(project: Project, mode: Mode, seed: int | None = None) -> TrackingRun:
    """Print the project's path on the simulated machine.

    Parameters
    ----------
    project
        A project whose elements include print paths, planned from one station.
    mode
        ``"closed"`` or ``"open"`` loop.
    seed
        Seed of the machine's errors and noise (``simulation.seed`` when ``None``);
        both modes run the same machine with the same errors.

    Raises
    ------
    InputError
        Without print paths, for a plan of more than one station, or a path out of reach.
    """
    settings = project.tracking
    if vendor_of(project.robot.name) != "heap":
        raise InputError(
            "'fabflow track' simulates a hydraulic excavator; use robot.model "
            f"'excavator_printer' (not {project.robot.model!r})",
            project.path,
            "robot.model",
        )
    elements = generate_elements(project.elements, project.path, project.limits)
    if not any(e.type == "print_path" for e in elements):
        raise InputError(
            "'fabflow track' follows print paths; the project has none", project.path, "elements"
        )
    plan = plan_project(project, elements)
    stations = {wp.station.id for wp in plan.work_packages}
    if len(stations) != 1:
        raise InputError(
            f"'fabflow track' follows a print from one station; the plan needs {len(stations)}",
            project.path,
            "elements",
        )
    in_plan = {e for wp in plan.work_packages for e in wp.elements}
    paths = [e for e in elements if e.id in in_plan and e.type == "print_path"]
    speeds = {float(e.attributes.get("speed", 0.1)) for e in paths}
    if len(speeds) != 1:
        raise InputError(
            "'fabflow track' follows one path at one speed; the print paths ask for "
            f"{sorted(speeds)} m/s",
            project.path,
            "elements",
        )
    speed = speeds.pop()
    ref = print_reference(paths, speed, RATE_HZ, settings.max_duration_s)
    robot = get_robot(project.robot.name)
    T_ft = project.robot.tool.T_flange_tool.matrix()
    T_wb = plan.work_packages[0].station.T_world_base(
        project.robot.platform.T_platform_base.matrix()
    )
    seed = project.simulation.seed if seed is None else seed
    machine_rng, noise_rng, lidar_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3)
    )
    errors = ExcavatorErrors() if project.simulation.sensor_noise else NO_ERRORS
    dt = 1.0 / RATE_HZ
    sensors = ExcavatorSensors(errors, robot.dof, dt, machine_rng, noise_rng)
    arm = true_arm(robot, errors, machine_rng)
    joints = HydraulicJoints(
        v_max=np.asarray(robot.velocity_limits, dtype=float),
        dead_time=settings.dead_time_s,
        tau=settings.lag_s,
        dt=dt,
        deadband=settings.deadband,
    )
    T_wb_believed = believed_base(T_wb, *sensors.base_error(0.0))
    ff = feed_forward(robot, ref, R_DOWN, T_wb_believed, T_ft)
    gains = TrackingGains(kp=settings.kp, ki=settings.ki) if mode == "closed" else None
    control = TrackingController(ff, ref, R_DOWN, T_wb_believed[:3, :3], joints, gains)
    machine = _Machine(arm, robot, T_wb, T_ft, ValveJoints(joints, ff.q[0]), sensors)
    return _loop(
        mode, ref, control, machine, round(settings.settle_s * RATE_HZ),
        settings.icp_latency_s, lidar_rng,
    )  # fmt: skip


def believed_base(T_wb: FloatArray, gnss: FloatArray, heading: float) -> FloatArray:
    """Where the machine believes its base is: the true base off by the GNSS error (metres,
    world frame) and turned by the heading error (radians, about the world's z axis)."""
    return perturb(T_wb, np.r_[gnss, 0.0, 0.0, heading])


def fusion_params(errors: ExcavatorErrors, robot: RobotModel) -> FusionParams:
    """The EKF's noise model for this machine's kinematics.

    The twist measured from two consecutive 100 Hz kinematic poses carries the
    white joint noise of both, over the arm's lever: ``sqrt(2 (dof - 1))
    sigma_joint reach / dt`` (m/s) and ``sqrt(2 (dof - 1)) sigma_joint / dt``
    (rad/s), at least the defaults' 2 cm/s and 0.01 rad/s.
    """
    base = FusionParams()
    s = np.sqrt(2.0 * (robot.dof - 1)) * np.radians(errors.joint_sigma_deg) * RATE_HZ
    return FusionParams(
        kin_velocity_sigma=max(base.kin_velocity_sigma, s * robot.reach),
        kin_rate_sigma=max(base.kin_rate_sigma, s),
    )


@dataclass(frozen=True, eq=False)
class _Machine:
    """The simulated machine: the arm as built and as modelled, where it stands, its state."""

    arm: RobotModel
    robot: RobotModel
    T_wb: FloatArray
    T_ft: FloatArray
    valves: ValveJoints
    sensors: ExcavatorSensors


def _loop(
    mode: Mode,
    ref: Reference,
    control: TrackingController,
    machine: _Machine,
    n_settle: int,
    latency: float,
    lidar_rng: np.random.Generator,
) -> TrackingRun:
    arm, robot, T_wb, T_ft = machine.arm, machine.robot, machine.T_wb, machine.T_ft
    valves, sensors = machine.valves, machine.sensors
    closed = mode == "closed"
    scene = site_scene() if closed else None
    site_map = simulated_site_map(registered=True) if closed else None
    K = len(ref.t)
    n = n_settle + K
    dt = 1.0 / RATE_HZ
    p_true = np.empty((n, 3))
    p_est = np.full((n, 3), np.nan)
    p_kin = np.empty((n, 3))
    p_icp = np.full((n, 3), np.nan)
    filt: IcpKinematicsFilter | None = None
    queue: deque[tuple[float, IcpFix]] = deque()
    counts = {"fixes": 0, "failed": 0}
    last_icp = np.full(3, np.nan)
    icp_error: list[FloatArray] = []
    # the heading error is constant: the believed base turns once, its position wanders
    T_wb_est = believed_base(T_wb, np.zeros(3), sensors.heading)
    wall0 = time.perf_counter()
    for k in range(n):
        t = k * dt
        q = valves.q
        T_true = T_wb @ arm.frames_single(q)[-1] @ T_ft
        gnss, _ = sensors.base_error(t)
        T_wb_est[:3, 3] = T_wb[:3, 3] + gnss
        q_meas = sensors.joints(t, q)
        T_kin = T_wb_est @ robot.frames_single(q_meas)[-1] @ T_ft
        if filt is None:
            filt = IcpKinematicsFilter(T_kin, fusion_params(sensors.errors, robot), t0=t)
        filt.kinematics(t, T_kin)
        if closed and k % ICP_EVERY == 0:
            fix = lidar_fix(scene, site_map, t, T_true, filt.pose, lidar_rng)
            counts["fixes"] += 1
            if fix.ok:
                queue.append((t + latency, fix))
                if k >= n_settle:
                    icp_error.append(fix.T_world_tool[:3, 3] - T_true[:3, 3])
            else:
                counts["failed"] += 1
        while queue and queue[0][0] <= t + 1e-9:
            _, fix = queue.popleft()
            filt.icp(fix.t, fix.T_world_tool, fix.covariance)
            last_icp = fix.T_world_tool[:3, 3]
        T_est = filt.pose
        valves.step(control.valves(k - n_settle, q_meas, T_est))
        p_true[k] = T_true[:3, 3]
        p_kin[k] = T_kin[:3, 3]
        p_est[k] = T_est[:3, 3]
        p_icp[k] = last_icp
    wall = time.perf_counter() - wall0
    c = {**counts, **(filt.counts if filt is not None else {})}
    nis = filt.nis_values if filt is not None else []
    s = slice(n_settle, n)
    return TrackingRun(
        mode=mode,
        t=ref.t,
        p_ref=ref.p,
        p_true=p_true[s],
        p_est=p_est[s],
        p_kin=p_kin[s],
        p_icp=p_icp[s],
        icp_error=np.reshape(icp_error, (-1, 3)),
        counts=c,
        mean_nis=float(np.mean(nis)) if len(nis) else float("nan"),
        simulated_s=n * dt,
        wall_s=wall,
    )
