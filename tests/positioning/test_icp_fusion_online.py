"""Online ICP/kinematics EKF: batch wrapper, delayed (out-of-sequence) ICP, gate, NIS."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fabflow.errors import InputError
from fabflow.positioning.icp_fusion import (
    FusionParams,
    IcpKinematicsFilter,
    fuse_icp_kinematics,
)
from fabflow.sensors.arm_motion import EndEffectorStreams, end_effector_streams
from fabflow.transforms.se3 import perturb
from fabflow.transforms.so3 import log_so3

DELAY = 8  # kinematics samples (0.08 s at 100 Hz) between a scan and its ICP pose


def streams(seed: int = 0, duration: float = 10.0) -> EndEffectorStreams:
    return end_effector_streams(np.random.default_rng(seed), duration=duration)


def state(f: IcpKinematicsFilter) -> np.ndarray:
    """Pose, pose covariance and twist of the filter as one flat array."""
    return np.concatenate([f.pose.ravel(), f.covariance.ravel(), f.twist])


def run(
    s: EndEffectorStreams, params: FusionParams | None = None, delay: int = 0
) -> tuple[IcpKinematicsFilter, np.ndarray, list[int]]:
    """Feed the streams, each ICP pose ``delay`` samples after its scan's sample.

    Returns the filter, its state after every kinematics sample (and the ICP poses
    that arrived then) and the samples at which ICP poses arrived.
    """
    f = IcpKinematicsFilter(s.T_kin[0], params, t0=s.t[0])
    scan_at = np.searchsorted(s.t, s.t_icp)  # the scans are taken at kinematics samples
    states, arrivals = [], []
    for k in range(len(s.t)):
        f.kinematics(s.t[k], s.T_kin[k])
        for j in np.flatnonzero(scan_at == k - delay):
            f.icp(s.t_icp[j], s.T_icp[j])
            arrivals.append(k)
        states.append(state(f))
    return f, np.array(states), arrivals


def test_batch_wrapper_matches_the_online_filter_and_the_former_batch_filter() -> None:
    # the wrapper feeds the filter as this loop does (a guard against the two drifting
    # apart); what can fail on a change of the filter's maths are the recorded values below
    s = streams(duration=3.0)
    fused = fuse_icp_kinematics(s.t, s.T_kin, s.t_icp, s.T_icp)
    f = IcpKinematicsFilter(s.T_icp[0], FusionParams(gate_alpha=None), t0=s.t[0])
    j = 0
    for k in range(len(s.t)):
        f.kinematics(s.t[k], s.T_kin[k])
        while j < len(s.t_icp) and s.t_icp[j] <= s.t[k]:
            assert f.icp(s.t[k], s.T_icp[j]).applied
            j += 1
        np.testing.assert_allclose(fused.T_world_ee[k], f.pose, rtol=0, atol=1e-12)
        np.testing.assert_allclose(fused.covariance[k], f.covariance, rtol=0, atol=1e-12)
        np.testing.assert_allclose(fused.twist[k], f.twist, rtol=0, atol=1e-12)
    # the last sample of the batch EKF before it became a wrapper of the online filter
    T = fused.T_world_ee[-1]
    np.testing.assert_allclose(
        T[:3, 3], [2.3194549559174087, 1.7559196065988754, 1.239568528224819], atol=1e-10
    )
    np.testing.assert_allclose(
        log_so3(T[:3, :3]),
        [0.005622475024455962, 0.001899881676607574, 2.8237599638280404],
        atol=1e-10,
    )
    np.testing.assert_allclose(
        fused.twist[-1],
        [
            -0.3545950394512129,
            0.11535439624737806,
            -0.11117271344221533,
            -0.019820399673420024,
            -0.0029429687812966426,
            0.3928474980286949,
        ],
        atol=1e-10,
    )
    np.testing.assert_allclose(
        np.diag(fused.covariance[-1]),
        [3.308572336471044e-06] * 3 + [1.7827371215963622e-06] * 3,
        rtol=1e-9,
    )


def test_batch_wrapper_ignores_the_gate() -> None:
    s = streams(duration=3.0)
    T_icp = s.T_icp.copy()
    T_icp[10] = perturb(T_icp[10], [1.0, 0, 0, 0, 0, 0])
    strict = FusionParams(gate_alpha=0.5)
    gated = fuse_icp_kinematics(s.t, s.T_kin, s.t_icp, T_icp, params=strict)
    default = fuse_icp_kinematics(s.t, s.T_kin, s.t_icp, T_icp)
    np.testing.assert_array_equal(gated.T_world_ee, default.T_world_ee)
    k = np.searchsorted(s.t, s.t_icp[10])
    assert np.linalg.norm(default.T_world_ee[k, :3, 3] - s.T_true[k, :3, 3]) > 0.1


def test_delayed_icp_refilter_equals_the_undelayed_filter() -> None:
    s = streams()
    on_time, states_on_time, _ = run(s)
    late, states_late, arrivals = run(s, delay=DELAY)
    assert len(arrivals) == len(s.t_icp) and arrivals[-1] < len(s.t) - 1
    assert not np.allclose(states_late[arrivals[3] - 1], states_on_time[arrivals[3] - 1])
    # right after each re-filter, the estimate is the one of the undelayed filter
    np.testing.assert_allclose(states_late[arrivals], states_on_time[arrivals], rtol=0, atol=1e-9)
    np.testing.assert_allclose(late.nis_values, on_time.nis_values, rtol=1e-9)
    np.testing.assert_allclose(state(late), state(on_time), rtol=0, atol=1e-9)
    assert late.counts == on_time.counts
    assert late.t == on_time.t == s.t[-1]


def test_icp_between_kinematics_samples_is_applied_at_its_time() -> None:
    s = streams(duration=2.0)
    k = 150  # a scan between samples k and k + 1, its pose 1 or 8 samples later
    t_scan = s.t[k] + 0.004
    results = []
    for lag in (1, DELAY):
        f = IcpKinematicsFilter(s.T_kin[0], t0=s.t[0])
        for i in range(k + 1 + lag):
            f.kinematics(s.t[i], s.T_kin[i])
        assert f.icp(t_scan, s.T_icp[15]).applied
        for i in range(k + 1 + lag, len(s.t)):
            f.kinematics(s.t[i], s.T_kin[i])
        results.append(state(f))
    np.testing.assert_allclose(results[0], results[1], rtol=0, atol=1e-9)
    # a scan a hair before sample k + 1 acts like one at k + 1, not like one at k: the
    # filter predicts to the scan's time instead of using the sample before it
    final = {}
    for t_stamp in (s.t[k], s.t[k + 1] - 1e-9, s.t[k + 1]):
        f = IcpKinematicsFilter(s.T_kin[0], t0=s.t[0])
        for i in range(k + 1 + DELAY):
            f.kinematics(s.t[i], s.T_kin[i])
        f.icp(t_stamp, s.T_icp[15])
        final[t_stamp] = state(f)
    np.testing.assert_allclose(final[s.t[k + 1] - 1e-9], final[s.t[k + 1]], rtol=0, atol=1e-6)
    assert np.abs(final[s.t[k]] - final[s.t[k + 1]]).max() > 1e-3


def test_gross_icp_outlier_is_gated_and_leaves_the_estimate_unchanged() -> None:
    s = streams(duration=2.0)
    f = IcpKinematicsFilter(s.T_kin[0], t0=s.t[0])
    for k in range(120):
        f.kinematics(s.t[k], s.T_kin[k])
    before = state(f)
    update = f.icp(s.t[110], perturb(s.T_true[110], [0.0, 1.0, 0.0, 0.0, 0.0, 0.0]))
    assert not update.applied and update.reason == "gated" and update.nis > 100
    np.testing.assert_array_equal(state(f), before)
    assert f.counts == {"icp_applied": 0, "icp_gated": 1, "icp_too_old": 0}
    assert f.nis_values == []
    update = f.icp(s.t[110], s.T_icp[11])  # the good pose of that scan still passes
    assert update.applied and update.reason == "ok" and update.nis < 30
    assert f.counts["icp_applied"] == 1 and f.nis_values == [update.nis]


def test_icp_older_than_the_history_is_rejected_as_too_old() -> None:
    s = streams(duration=2.0)
    f = IcpKinematicsFilter(s.T_kin[0], t0=s.t[0], history_s=0.5)
    for k in range(150):
        f.kinematics(s.t[k], s.T_kin[k])
    before = state(f)
    update = f.icp(f.t - 0.6, s.T_icp[8])
    assert not update.applied and update.reason == "too old" and math.isnan(update.nis)
    np.testing.assert_array_equal(state(f), before)
    assert f.icp(f.t - 0.45, s.T_icp[10]).applied  # within the history
    g = IcpKinematicsFilter(s.T_kin[0], t0=1.0)
    assert g.icp(0.5, s.T_kin[0]).reason == "too old"  # before the filter's start
    assert g.counts == {"icp_applied": 0, "icp_gated": 0, "icp_too_old": 1}


def test_online_filter_input_checks() -> None:
    s = streams(duration=0.5)
    f = IcpKinematicsFilter(s.T_kin[0], t0=s.t[1])
    with pytest.raises(InputError):
        f.kinematics(s.t[0], s.T_kin[0])  # before t0
    f.kinematics(s.t[1], s.T_kin[1])
    for t in (s.t[1], s.t[0], math.nan):
        with pytest.raises(InputError):
            f.kinematics(t, s.T_kin[2])
    with pytest.raises(InputError):
        f.kinematics(s.t[2], s.T_kin[2, :3])
    with pytest.raises(InputError):
        f.kinematics(s.t[2], np.full((4, 4), np.nan))
    with pytest.raises(InputError):
        f.icp(s.t[1], s.T_icp[0], covariance=np.eye(3))
    with pytest.raises(InputError):
        IcpKinematicsFilter(s.T_kin[0], FusionParams(gate_alpha=1.5))
    with pytest.raises(InputError):
        IcpKinematicsFilter(s.T_kin[0], history_s=-1.0)


def test_mean_nis_of_the_applied_icp_poses_is_consistent() -> None:
    s = streams()
    f, _, _ = run(s, delay=DELAY)
    applied, gated = f.counts["icp_applied"], f.counts["icp_gated"]
    mean_nis = float(np.mean(f.nis_values))
    # 8.5 here, not 6: the simulated ICP error is 5.8 mm per axis while the default
    # ICP covariance says 5 mm (x1.35 on the 3 position terms), and the kinematic
    # pose noise (1 mm white per sample, plus a slowly varying bias) is not the
    # white twist noise the filter assumes. The rotation part alone averages 3.0,
    # as it should. A band of 0.75 to 2 times 6 holds that and fails when the ICP
    # covariance is off by a factor 4 either way (checked below).
    assert 4.5 < mean_nis < 12.0, mean_nis
    assert gated <= 0.02 * (applied + gated), f.counts
    base = np.array(FusionParams().icp_covariance)
    too_large, _, _ = run(s, FusionParams(icp_covariance=tuple(4 * base)), delay=DELAY)
    assert np.mean(too_large.nis_values) < 4.5
    too_small, _, _ = run(s, FusionParams(icp_covariance=tuple(base / 4)), delay=DELAY)
    assert too_small.counts["icp_gated"] > 0.02 * len(s.t_icp)
