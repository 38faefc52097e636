"""The printing excavator of paper 000 as a simulated machine: its errors and its sensors.

The truth is a hydraulic arm (:class:`~fabflow.robots.hydraulic.ValveJoints`)
whose geometry differs from the catalogue model by a calibration error, on a
base whose pose the GNSS knows only to a slowly wandering error. What the
machine measures (paper 000, sections II and III-A):

* the **turn joint** by counting 98 gear teeth (0.92 deg steps) and by the
  difference of the cabin and chassis gyros, fused by
  :class:`~fabflow.positioning.turn_joint.TurnJointKF`;
* **boom, stick and the tilt-rotator's joints** by wire encoders on the
  cylinders and IMUs on the links: white noise plus a constant bias per joint
  (the mounting of the link IMUs);
* the **base pose** by RTK GNSS and the cabin IMU: a smooth, slowly wandering
  error per axis (the paper: "between 1 up to 10 cm"), the sum of three
  sinusoids of random phase with periods between ``gnss_period_s``, as the
  machine's state estimator gives it for a base standing still, and a constant
  heading error.

The values of :class:`ExcavatorErrors` are stated with their source there;
the ones the paper does not give are assumptions, named as such.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from fabflow.positioning.turn_joint import ENCODER_RESOLUTION, TurnJointKF, quantize
from fabflow.robots.chain import RobotModel

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ExcavatorErrors:
    """Error model of the printing excavator (SI units, angles in degrees where named).

    Attributes
    ----------
    joint_sigma_deg
        White noise of the boom, stick and wrist angles per 100 Hz sample
        (assumption: a wire encoder's 0.1 mm resolution on a cylinder about 1 m
        from its joint gives 0.0057 deg steps, whose uniform error has a sigma
        of 0.0017 deg).
    joint_bias_deg
        Standard deviation of each of those joints' constant bias (assumption:
        IMU mounting, a tenth of a degree).
    gyro_sigma, gyro_bias_sigma
        White noise per sample and constant bias of each turn-joint gyro (rad/s;
        as in :func:`~fabflow.sensors.arm_motion.turn_joint_streams`).
    gnss_sigma_xy, gnss_sigma_z
        Standard deviation of the base position error per horizontal axis and
        vertically (metres; RTK GNSS, paper 000: "between 1 up to 10 cm"). The
        horizontal one is fitted on paper 000's kinematics-only RMSE (section
        IV-A, 2.23 cm; ``benchmarks/sensor_models.py``), the vertical one kept at
        4/3 of it; RTK receivers are specified at about 8 mm + 1 ppm horizontal
        and 15 mm + 1 ppm vertical.
    gnss_period_s
        Shortest and longest period of that error's sinusoids (s; multipath and
        satellite geometry change over minutes).
    heading_sigma_deg
        Constant heading error of the base (two-antenna GNSS, assumption).
    link_sigma
        Standard deviation of the boom's and stick's true lengths about the
        model's (metres; calibration, assumption).
    """

    joint_sigma_deg: float = 0.002
    joint_bias_deg: float = 0.1
    gyro_sigma: float = 0.007
    gyro_bias_sigma: float = 0.002
    gnss_sigma_xy: float = 0.0075
    gnss_sigma_z: float = 0.01
    gnss_period_s: tuple[float, float] = (30.0, 120.0)
    heading_sigma_deg: float = 0.1
    link_sigma: float = 0.005


NO_ERRORS = ExcavatorErrors(
    joint_sigma_deg=0.0,
    joint_bias_deg=0.0,
    gyro_sigma=0.0,
    gyro_bias_sigma=0.0,
    gnss_sigma_xy=0.0,
    gnss_sigma_z=0.0,
    heading_sigma_deg=0.0,
    link_sigma=0.0,
)
"""A perfect machine: exact joints, base and geometry (the turn encoder still quantizes)."""


def true_arm(robot: RobotModel, errors: ExcavatorErrors, rng: np.random.Generator) -> RobotModel:
    """The machine as built: the model with the boom and stick lengths off by ``link_sigma``.

    The closed-form IK is dropped: it belongs to the nominal lengths.
    """
    dh = robot.dh.copy()
    dh[1:3, 0] += rng.normal(0.0, errors.link_sigma, 2)
    return replace(robot, dh=dh, analytic_ik=None)


class ExcavatorSensors:
    """The machine's measurements of its joints and base, one 100 Hz sample at a time.

    Parameters
    ----------
    errors
        The error model.
    dof
        Number of joints (joint 0 is the turn joint).
    dt
        Sample period (s).
    rng
        Source of the biases and the GNSS error's phases (drawn here).
    noise_rng
        Source of the noise of every sample (default ``rng``).
    """

    def __init__(
        self,
        errors: ExcavatorErrors,
        dof: int,
        dt: float,
        rng: np.random.Generator,
        noise_rng: np.random.Generator | None = None,
    ) -> None:
        self.errors = errors
        self.dt = dt
        self.rng = rng if noise_rng is None else noise_rng
        self.joint_bias = np.radians(rng.normal(0.0, errors.joint_bias_deg, dof))
        self.joint_bias[0] = 0.0
        self.gyro_bias = float(np.subtract(*rng.normal(0.0, errors.gyro_bias_sigma, 2)))
        self.heading = np.radians(rng.normal(0.0, errors.heading_sigma_deg))
        sig = np.array([errors.gnss_sigma_xy, errors.gnss_sigma_xy, errors.gnss_sigma_z])
        # three sinusoids per axis, each of amplitude sigma sqrt(2 / 3): std sigma
        self._gnss_amp = np.sqrt(2.0 / 3.0) * np.broadcast_to(sig, (3, 3)).T
        self._gnss_omega = 2 * np.pi / rng.uniform(*errors.gnss_period_s, (3, 3))
        self._gnss_phase = rng.uniform(0.0, 2 * np.pi, (3, 3))
        self._turn = TurnJointKF(gyro_sigma=max(np.sqrt(2.0) * errors.gyro_sigma, 1e-6))
        self._turn_state: tuple[FloatArray, FloatArray] | None = None
        self._last_turn: float | None = None

    def base_error(self, t: float) -> tuple[FloatArray, float]:
        """The base's error at time ``t`` (s): ``(position error (3,) m, heading error rad)``."""
        gnss = np.sum(self._gnss_amp * np.sin(self._gnss_omega * t + self._gnss_phase), axis=1)
        return gnss, self.heading

    def joints(self, t: float, q_true: FloatArray) -> FloatArray:
        """What the machine reads of its joints at time ``t`` (radians).

        Joint 0 is the turn-joint KF's estimate from the tooth-counting encoder
        and the gyro difference; the others are the truth plus bias and noise.
        """
        e = self.errors
        q = (
            q_true
            + self.joint_bias
            + np.radians(e.joint_sigma_deg) * self.rng.normal(0.0, 1.0, q_true.shape)
        )
        rate = 0.0 if self._last_turn is None else (q_true[0] - self._last_turn) / self.dt
        self._last_turn = float(q_true[0])
        gyro = rate + self.gyro_bias + np.sqrt(2.0) * e.gyro_sigma * self.rng.normal()
        enc = float(quantize(q_true[0], ENCODER_RESOLUTION))
        if self._turn_state is None:
            self._turn_state = self._turn.start(enc, gyro)
            dt = 0.0  # the first sample: nothing to predict over, as TurnJointKF.run
        else:
            dt = self.dt
        self._turn_state = self._turn.step(*self._turn_state, dt, enc, gyro)
        q[0] = self._turn_state[0][0]
        return q
