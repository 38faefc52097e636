"""The stepped hydraulic joints: dead time, lag, saturation and the valve's deadband."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.robots.hydraulic import HydraulicJoints, ValveJoints

V = np.array([0.5, 0.3])


def test_a_command_acts_after_the_dead_time_and_settles_at_its_flow() -> None:
    j = HydraulicJoints(v_max=V, dead_time=0.1, tau=0.05, dt=0.01)
    valves = ValveJoints(j, [0.0, 0.0])
    q = [valves.step([0.5, -2.0]).copy() for _ in range(300)]
    assert np.all(np.asarray(q[:10]) == 0.0)  # 10 steps of dead time
    assert np.all(q[10] != 0.0)  # and not one more
    v = (q[-1] - q[-2]) / j.dt
    assert v == pytest.approx([0.25, -0.3])  # 0.5 of the flow; -2 saturates at -1


@given(u=st.floats(-1.0, 1.0), db=st.floats(0.0, 0.5))
@settings(max_examples=60, deadline=None)
def test_the_deadband_swallows_small_openings_and_rescales_the_rest(u: float, db: float) -> None:
    j = HydraulicJoints(v_max=V, dead_time=0.0, tau=0.0, dt=0.01, deadband=db)
    valves = ValveJoints(j, [0.0, 0.0])
    v = valves.step([u, u]) / j.dt
    expected = np.sign(u) * max(abs(u) - db, 0.0) / (1.0 - db) * V
    assert v == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize(
    "bad", [{"deadband": 1.0}, {"deadband": -0.1}, {"dead_time": -1.0}, {"dt": 0.0}]
)
def test_bad_parameters_are_refused(bad) -> None:
    with pytest.raises(InputError):
        HydraulicJoints(v_max=V, **bad)
