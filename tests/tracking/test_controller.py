"""The tracking controller removes a kinematic bias and settles at the hydraulic delay."""

from __future__ import annotations

import numpy as np
import pytest

from fabflow.robots.catalog import get_robot
from fabflow.robots.hydraulic import HydraulicJoints, ValveJoints
from fabflow.tracking.controller import TrackingController, TrackingGains, feed_forward
from fabflow.tracking.reference import R_DOWN, Reference
from fabflow.transforms.se3 import make_T

ROBOT = get_robot("excavator_printer")
T_FT = make_T(np.eye(3), [0.0, 0.0, 0.6])
RATE = 100.0


def _hold(p: np.ndarray, seconds: float) -> Reference:
    n = round(seconds * RATE)
    return Reference(
        t=np.arange(n) / RATE,
        p=np.tile(p, (n, 1)),
        v=np.zeros((n, 3)),
        extrude=np.ones(n, bool),
        length=0.0,
    )


def _step_response(dead_time: float, lag: float, offset: np.ndarray, seconds: float = 40.0):
    """The machine holds a point while its true base is ``offset`` from the believed one.

    The controller sees the true nozzle (a perfect estimate) 0.1 s late, as it
    sees a LiDAR fix; returns the nozzle's error against the reference over time.
    """
    ref = _hold(np.array([4.5, -2.0, 0.1]), seconds)
    T_wb_believed = np.eye(4)
    T_wb_true = make_T(np.eye(3), offset)
    joints = HydraulicJoints(
        v_max=ROBOT.velocity_limits, dead_time=dead_time, tau=lag, dt=1 / RATE, deadband=0.02
    )
    ff = feed_forward(ROBOT, ref, R_DOWN, T_wb_believed, T_FT)
    control = TrackingController(ff, ref, R_DOWN, np.eye(3), joints, TrackingGains(kp=0.5, ki=0.5))
    valves = ValveJoints(joints, ff.q[0])
    delay = 10
    seen: list[np.ndarray] = []
    err = np.empty((len(ref.t), 3))
    for k in range(len(ref.t)):
        T_true = T_wb_true @ ROBOT.fk(valves.q) @ T_FT
        seen.append(T_true)
        err[k] = T_true[:3, 3] - ref.p[k]
        valves.step(control.valves(k, valves.q, seen[max(0, k - delay)]))
    return ref.t, np.linalg.norm(err, axis=1)


@pytest.mark.parametrize("dead_time", [0.08, 0.16])
def test_a_kinematic_bias_is_removed_without_sustained_oscillation(dead_time: float) -> None:
    t, e = _step_response(dead_time, 0.1, np.array([0.03, -0.02, 0.01]))
    e0 = e[0]
    assert e0 > 0.035  # the bias is there at the start
    last = t > t[-1] - 10.0
    assert e[last].max() < 0.05 * e0  # settled to within 5 % of the step
    # no sustained oscillation: the error keeps falling, it does not ring
    assert np.ptp(e[last]) < 0.02 * e0 + 5e-4
    assert e.max() < 1.3 * e0  # and it never overshoots far


def test_open_loop_keeps_the_bias() -> None:
    ref = _hold(np.array([4.5, -2.0, 0.1]), 10.0)
    joints = HydraulicJoints(v_max=ROBOT.velocity_limits, dead_time=0.08, tau=0.1, dt=0.01)
    ff = feed_forward(ROBOT, ref, R_DOWN, np.eye(4), T_FT)
    control = TrackingController(ff, ref, R_DOWN, np.eye(3), joints, None)
    valves = ValveJoints(joints, ff.q[0])
    offset = np.array([0.03, -0.02, 0.01])
    for k in range(len(ref.t)):
        T = make_T(np.eye(3), offset) @ ROBOT.fk(valves.q) @ T_FT
        valves.step(control.valves(k, valves.q, T))
    assert np.linalg.norm(T[:3, 3] - ref.p[-1] - offset) < 1e-3  # the joints hold, the bias stays


def test_the_deadband_is_inverted_so_small_commands_still_move() -> None:
    ref = _hold(np.array([4.5, -2.0, 0.1]), 1.0)
    joints = HydraulicJoints(v_max=ROBOT.velocity_limits, dead_time=0.0, tau=0.0, deadband=0.1)
    ff = feed_forward(ROBOT, ref, R_DOWN, np.eye(4), T_FT)
    control = TrackingController(ff, ref, R_DOWN, np.eye(3), joints, None)
    q = ff.q[0] - 0.001  # 1 mrad short on every joint
    u = control.valves(0, q, None)
    valves = ValveJoints(joints, q)
    v = (valves.step(u) - q) / joints.dt
    assert np.allclose(v, control.k_joint * 0.001, rtol=1e-9)
