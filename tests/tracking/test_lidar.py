"""The print head's LiDAR fix: a scan of the site registered to its map."""

from __future__ import annotations

import numpy as np
import pytest

from fabflow.sensors.site_map import simulated_site_map
from fabflow.sensors.site_scene import site_scene
from fabflow.tracking.lidar import lidar_fix
from fabflow.tracking.reference import R_DOWN
from fabflow.transforms.se3 import make_T, perturb, pose_error


@pytest.fixture(scope="module")
def site():
    return site_scene(), simulated_site_map(registered=True)


def test_a_fix_from_a_nearby_guess_recovers_the_pose_with_its_covariance(site) -> None:
    scene, site_map = site
    rng = np.random.default_rng(0)
    errors, nis = [], []
    for i in range(20):
        T = make_T(R_DOWN, [4.0 + 0.1 * i, -0.8, 0.1])
        guess = perturb(T, np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.003, 3)])
        fix = lidar_fix(scene, site_map, 0.0, T, guess, rng)
        assert fix.ok
        e = pose_error(fix.T_world_tool, T)
        errors.append(np.linalg.norm(e[:3]))
        assert np.all(np.linalg.eigvalsh(fix.covariance) > 0)
        nis.append(e @ np.linalg.solve(fix.covariance, e))
    assert np.sqrt(np.mean(np.square(errors))) < 0.008  # millimetres, not centimetres
    assert 1.0 < np.mean(nis) < 20.0  # the covariance is neither absurdly small nor large


def test_a_guess_far_off_gives_no_fix_instead_of_an_error(site) -> None:
    scene, site_map = site
    T = make_T(R_DOWN, [4.5, -0.8, 0.1])
    far = make_T(R_DOWN, [40.0, 40.0, 30.0])
    fix = lidar_fix(scene, site_map, 1.0, T, far, np.random.default_rng(1))
    assert not fix.ok
