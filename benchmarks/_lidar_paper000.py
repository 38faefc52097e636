"""Paper 000's LiDAR scenarios on the simulated site, for ``sensor_models.py``.

Not a benchmark itself (``tests/test_benchmarks.py`` runs every script but ``_`` modules).

* **Table I, outdoor**: a stationary LiDAR, localized in the site map run after
  run "at different times of the day"; the table gives the mean deviation of
  the recorded poses per axis. Simulated: the sensor 2.5 m above the middle of
  the site (its landmarks 5-15 m away), each run with its own channel biases,
  noise and clutter, localized by the fine ICP stage from the pose off by 2 cm
  and 0.5 deg; the deviation is each run's pose from the runs' mean.
* **Section IV-A**: the LiDAR on the excavator's end-effector, steered by hand
  along an arbitrary trajectory, its ICP poses against a total station: RMSE
  0.58 cm. Simulated: the sensor on a 4 m radius about the cabin's slewing axis,
  slewing at 0.05 rad/s (0.2 m/s at the sensor) while rising and sinking 0.5 m
  every 10 s, 2.5 m above the ground on average, facing along its path, each
  10 Hz scan distorted by that motion (no de-skewing), one run's channel biases,
  matched to a map that a mapping run built with the same sensor (registered
  scan after scan, so it drifts); each scan localized by the fine ICP stage
  from the pose off by 2 cm and 0.5 deg (the kinematic prediction); the RMSE of
  the 3D position against the true pose at mid-revolution, over several runs
  (each its own channel biases) spread round the circle. The paper gives no
  speeds; these are assumptions, not fitted.
* **Section IV-A, kinematics only**: the same experiment's baseline, the
  end-effector from the machine's joint sensors, GNSS base and calibrated arm
  (RMSE 2.23 cm). Simulated with the machine ``fabflow track`` simulates
  (:class:`~fabflow.sensors.excavator.ExcavatorErrors`, none of its terms fitted
  here): each run a machine with its own biases, link lengths and GNSS wander,
  its arm slewing at the rate above while the boom heaves the tool 0.5 m every
  10 s and the stick and wrist swing on periods of their own (the paper steered
  by hand; these motions are assumptions), 60 s at 100 Hz; the RMSE of the
  kinematic tool position against the true one over every sample of every run,
  its largest error and its share of axis errors within +-1 cm.
"""

from __future__ import annotations

import numpy as np

from fabflow.errors import LocalizationError
from fabflow.positioning.scan_map import ScanMap
from fabflow.positioning.scan_matching import localize_scan
from fabflow.robots.catalog import get_robot
from fabflow.sensors.excavator import ExcavatorErrors, ExcavatorSensors, true_arm
from fabflow.sensors.lidar import HESAI_QT64, simulate_scan
from fabflow.sensors.lidar_errors import LidarErrorModel, draw_channel_bias
from fabflow.sensors.site_map import simulated_site_map
from fabflow.sensors.site_scene import site_scene
from fabflow.tracking.run import RATE_HZ, believed_base
from fabflow.transforms.se3 import make_T, perturb, pose_error
from fabflow.transforms.so3 import exp_so3

TABLE_I_OUTDOOR_CM = {"x": 0.35, "y": 0.47, "z": 0.19}
"""Paper 000, table I, outdoor: mean position deviation of a stationary LiDAR (cm)."""
TABLE_I_OUTDOOR_DEG = {"roll": 0.34, "pitch": 0.61, "yaw": 0.45}
"""The same for the orientation (degrees)."""
ICP_RMSE_CM = 0.58
"""Paper 000, section IV-A: ICP end-effector position RMSE on the moving excavator (cm)."""
KINEMATICS_RMSE_CM = 2.23
"""The same for the kinematics-only estimate (cm)."""
KINEMATICS_MAX_CM = 6.61
"""Its largest error (cm; the paper prints "6.61 mm", which cannot be below its RMSE)."""
KINEMATICS_WITHIN_1CM = 0.49
"""Its share of the time within +-1 cm of the truth (read here per axis)."""

CENTRE = np.array([2.0, 1.65])
"""The middle of the simulated site (the default cabin's footprint), metres."""
STATIC_POSE = make_T(np.eye(3), [CENTRE[0], CENTRE[1], 2.5])
SLEW_RADIUS, SLEW_RATE, HEIGHT, HEAVE, HEAVE_PERIOD = 4.0, 0.05, 2.5, 0.5, 10.0
ARM_START = np.array([0.0, 0.8, -1.7, 0.0, 0.0, 0.0])
"""The excavator's joints (rad) at the start of the kinematics run: the tool 5.1 m
from the slewing axis, 2.4 m above the base."""
ARM_SWING = np.array([0.0, 0.1, 0.2, 0.2, 0.15, 0.3])
"""Amplitudes (rad) of the joints' swings about :data:`ARM_START` (boom: the 0.5 m heave)."""
ARM_PERIOD = np.array([1.0, HEAVE_PERIOD, 17.0, 7.0, 11.0, 13.0])
"""Their periods (s)."""
TOOL = make_T(np.eye(3), [0.0, 0.0, 0.6])
"""Flange to tool: ``projects/excavator_print``'s print head."""
GUESS_ERROR = (0.02, 0.5)
"""The initial guess of each localization: metres per axis, degrees per angle."""


def _guess(T: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    err = np.r_[rng.normal(0.0, GUESS_ERROR[0], 3), rng.normal(0.0, np.radians(GUESS_ERROR[1]), 3)]
    return perturb(T, err)


def _localize(
    points: np.ndarray, site_map: ScanMap, T: np.ndarray, rng: np.random.Generator
) -> np.ndarray | None:
    """The fine ICP stage from ``T`` off by :data:`GUESS_ERROR`; ``None`` when it fails."""
    try:
        loc = localize_scan(points, site_map, _guess(T, rng), coarse_schedule=None)
    except LocalizationError:
        return None
    return None if loc.integrity.failed else loc.T_world_lidar


def static_deviation(
    errors: LidarErrorModel, runs: int, seed: int
) -> tuple[np.ndarray, np.ndarray, int]:
    """Table I's figures simulated: mean absolute deviation of the runs' poses from their
    mean, position ``(3,)`` metres and orientation ``(3,)`` degrees (roll, pitch, yaw),
    and the number of runs that failed."""
    rng = np.random.default_rng(seed)
    site_map = simulated_site_map(errors=errors, registered=True)
    scene = site_scene()
    poses, failed = [], 0
    for _ in range(runs):
        bias = draw_channel_bias(errors, HESAI_QT64.n_beams, rng)
        scan = simulate_scan(scene, STATIC_POSE, rng, HESAI_QT64, errors, bias)
        T = _localize(scan.points, site_map, STATIC_POSE, rng)
        if T is None:
            failed += 1
            continue
        poses.append(pose_error(T, STATIC_POSE))
    e = np.array(poses)
    dev = np.abs(e - e.mean(axis=0)).mean(axis=0)
    return dev[:3], np.degrees(dev[3:]), failed


def _slew_pose(t: float) -> tuple[np.ndarray, np.ndarray]:
    """Sensor pose and twist (world frame: m/s then rad/s) on the slewing trajectory."""
    a = SLEW_RATE * t
    w = 2 * np.pi / HEAVE_PERIOD
    p = [
        CENTRE[0] + SLEW_RADIUS * np.cos(a),
        CENTRE[1] + SLEW_RADIUS * np.sin(a),
        HEIGHT + HEAVE * np.sin(w * t),
    ]
    v = [
        -SLEW_RADIUS * SLEW_RATE * np.sin(a),
        SLEW_RADIUS * SLEW_RATE * np.cos(a),
        HEAVE * w * np.cos(w * t),
    ]
    T = make_T(exp_so3([0.0, 0.0, a + np.pi / 2]), p)
    return T, np.r_[v, 0.0, 0.0, SLEW_RATE]


def moving_rmse(errors: LidarErrorModel, runs: int, scans: int, seed: int) -> tuple[float, int]:
    """Section IV-A's figure simulated: the RMSE (metres) of the ICP positions over
    ``runs`` runs (each with its own channel biases, the trajectory started further
    along) of ``scans`` 10 Hz scans, and the number of scans that failed."""
    rng = np.random.default_rng(seed)
    site_map = simulated_site_map(errors=errors, registered=True)
    scene = site_scene()
    sq, failed = [], 0
    for run in range(runs):
        bias = draw_channel_bias(errors, HESAI_QT64.n_beams, rng)
        start = run * 2 * np.pi / (SLEW_RATE * max(runs, 1))  # spread round the circle
        for k in range(scans):
            T, twist = _slew_pose(start + k / HESAI_QT64.rate_hz)
            scan = simulate_scan(scene, T, rng, HESAI_QT64, errors, bias, twist)
            est = _localize(scan.points, site_map, T, rng)
            if est is None:
                failed += 1
                continue
            sq.append(np.sum((est[:3, 3] - T[:3, 3]) ** 2))
    return float(np.sqrt(np.mean(sq))) if sq else float("nan"), failed


def _arm_joints(t: np.ndarray) -> np.ndarray:
    """``(S, 6)`` joints (rad) of the kinematics run at times ``t`` (s)."""
    q = ARM_START + ARM_SWING * np.sin(2 * np.pi * t[:, None] / ARM_PERIOD)
    q[:, 0] = SLEW_RATE * t
    return q


def kinematics_errors(errors: ExcavatorErrors, runs: int, seconds: float, seed: int) -> np.ndarray:
    """Section IV-A's kinematics-only estimate simulated: ``(runs, S, 3)`` errors
    (metres, world frame) of the tool position the machine's kinematics give
    against the true one, every 100 Hz sample of ``runs`` machines (each its own
    errors) moving for ``seconds``."""
    robot = get_robot("excavator_printer")
    dt = 1.0 / RATE_HZ
    t = np.arange(round(seconds * RATE_HZ)) * dt
    q = _arm_joints(t)
    T_wb = make_T(np.eye(3), [CENTRE[0], CENTRE[1], 0.0])
    out = []
    for s in np.random.SeedSequence(seed).spawn(runs):
        # drawn in the order 'fabflow track' draws them: the sensors, then the arm
        machine_rng, noise_rng = (np.random.default_rng(c) for c in s.spawn(2))
        sensors = ExcavatorSensors(errors, robot.dof, dt, machine_rng, noise_rng)
        arm = true_arm(robot, errors, machine_rng)
        q_meas = np.array([sensors.joints(tk, qk) for tk, qk in zip(t, q, strict=True)])
        bases = np.array([believed_base(T_wb, *sensors.base_error(tk)) for tk in t])
        p_true = (T_wb @ arm.frames(q)[:, -1] @ TOOL)[:, :3, 3]
        p_kin = (bases @ robot.frames(q_meas)[:, -1] @ TOOL)[:, :3, 3]
        out.append(p_kin - p_true)
    return np.stack(out)
