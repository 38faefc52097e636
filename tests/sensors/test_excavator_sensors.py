"""The printing excavator's error model: what the machine reads of its joints and base."""

from __future__ import annotations

import numpy as np
import pytest

from fabflow.positioning.turn_joint import ENCODER_RESOLUTION
from fabflow.robots.catalog import get_robot
from fabflow.sensors.excavator import NO_ERRORS, ExcavatorErrors, ExcavatorSensors, true_arm

ROBOT = get_robot("excavator_printer")


def test_a_perfect_machine_reads_its_joints_to_the_turn_encoders_steps() -> None:
    s = ExcavatorSensors(NO_ERRORS, 6, 0.01, np.random.default_rng(0))
    t = np.arange(0, 20, 0.01)
    slew = 0.3 * np.sin(2 * np.pi * t / 20)
    err = []
    for ti, a in zip(t, slew, strict=True):
        q = np.array([a, 0.2, -1.2, -0.5, 0.0, 0.0])
        m = s.joints(ti, q)
        assert np.array_equal(m[1:], q[1:])
        err.append(m[0] - a)
    # the KF with the gyro difference does far better than the 0.92 deg steps
    assert np.sqrt(np.mean(np.square(err[200:]))) < 0.25 * ENCODER_RESOLUTION
    assert s.base_error(5.0)[0] == pytest.approx(np.zeros(3))


def test_the_gnss_error_wanders_slowly_with_its_sigma() -> None:
    e = ExcavatorErrors()
    rows = []
    for seed in range(40):
        s = ExcavatorSensors(e, 6, 0.01, np.random.default_rng(seed))
        rows.append([s.base_error(t)[0] for t in np.arange(0.0, 600.0, 5.0)])
    g = np.asarray(rows)  # (runs, 10 minutes every 5 s, 3)
    assert np.std(g[..., 0]) == pytest.approx(e.gnss_sigma_xy, rel=0.25)
    assert np.std(g[..., 2]) == pytest.approx(e.gnss_sigma_z, rel=0.25)
    # smooth: 10 ms apart it moves far less than a millimetre
    s = ExcavatorSensors(e, 6, 0.01, np.random.default_rng(0))
    a, b = s.base_error(10.0)[0], s.base_error(10.01)[0]
    assert np.linalg.norm(b - a) < 1e-4
    # but it wanders: over a minute it moves by about its sigma
    moves = [np.linalg.norm(s.base_error(t + 60.0)[0] - s.base_error(t)[0]) for t in (0, 100, 200)]
    assert max(moves) > 0.3 * e.gnss_sigma_xy


def test_the_machine_as_built_differs_from_the_model_by_its_calibration() -> None:
    arm = true_arm(ROBOT, ExcavatorErrors(), np.random.default_rng(3))
    d = arm.dh[:, 0] - ROBOT.dh[:, 0]
    assert np.count_nonzero(d) == 2 and np.all(np.abs(d[1:3]) < 0.03)
    assert arm.analytic_ik is None
    assert np.array_equal(true_arm(ROBOT, NO_ERRORS, np.random.default_rng(3)).dh, ROBOT.dh)
