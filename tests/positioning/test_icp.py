"""ICP registration: accuracy, robustness, covariance, failure modes."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import icp_room as room
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.icp import icp, prepare_target
from fabflow.positioning.icp_weakness import weakest_direction
from fabflow.transforms.se3 import apply_T, inv_T, perturb, pose_error


@pytest.fixture(scope="module")
def target() -> np.ndarray:
    return room(np.random.default_rng(0), 3000)


def make_source(
    target_rng_seed: int, T_true: np.ndarray, noise: float = 0.003, n: int = 600
) -> np.ndarray:
    rng = np.random.default_rng(target_rng_seed)
    pts = room(rng, n)
    src = apply_T(inv_T(T_true), pts)
    return src + rng.normal(0, noise, src.shape)


@pytest.mark.parametrize("method", ["point_to_plane", "point_to_point"])
def test_recovers_known_transform(target: np.ndarray, method: str) -> None:
    T_true = perturb(np.eye(4), [0.2, -0.15, 0.05, 0.02, -0.03, 0.12])
    res = icp(make_source(5, T_true), target, method=method, max_iterations=60)
    err = pose_error(res.T, T_true)
    # point-to-point is biased by the target's 9 cm point spacing
    tol = 3e-3 if method == "point_to_plane" else 1e-2
    assert np.all(np.abs(err[:3]) < tol), err
    assert np.all(np.abs(err[3:]) < 2e-3), err
    assert res.fitness > 0.99
    assert 0 < res.inlier_rmse < (0.02 if method == "point_to_plane" else 0.06)
    assert res.iterations >= 1
    assert res.covariance.shape == (6, 6)
    np.testing.assert_allclose(res.covariance, res.covariance.T, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(res.covariance) > 0)
    assert res.condition > 1e-4


@settings(deadline=None, max_examples=10)
@given(
    st.lists(st.floats(-0.25, 0.25), min_size=3, max_size=3),
    st.floats(-0.15, 0.15),
    st.integers(0, 1000),
)
def test_point_to_plane_converges_from_random_offsets(
    target: np.ndarray, dt: list[float], yaw: float, seed: int
) -> None:
    T_true = perturb(np.eye(4), [*dt, 0.0, 0.0, yaw])
    res = icp(make_source(seed, T_true), target)
    assert np.linalg.norm(pose_error(res.T, T_true)[:3]) < 5e-3


def test_initial_guess_is_used(target: np.ndarray) -> None:
    T_true = perturb(np.eye(4), [1.5, 1.0, 0.0, 0.0, 0.0, 0.6])
    src = make_source(7, T_true)
    blind = icp(src, target, max_correspondence_distance=0.1)
    assert np.linalg.norm(pose_error(blind.T, T_true)[:3]) > 0.1
    init = perturb(T_true, [0.05, -0.05, 0.0, 0.0, 0.0, 0.02])
    res = icp(src, target, init=init, max_correspondence_distance=(0.3, 0.1))
    assert np.linalg.norm(pose_error(res.T, T_true)[:3]) < 5e-3


def test_no_overlap_fails_loudly(target: np.ndarray) -> None:
    with pytest.raises(LocalizationError, match="correspondences"):
        icp(target[::10] + np.array([100.0, 0.0, 0.0]), target)


def test_robust_kernel_handles_outliers(target: np.ndarray) -> None:
    rng = np.random.default_rng(3)
    T_true = perturb(np.eye(4), [0.1, 0.1, 0.0, 0.0, 0.0, 0.05])
    src = make_source(3, T_true)
    clutter = rng.uniform([1, 1, 0], [5, 3, 2], (1500, 3))
    res = icp(np.vstack([src, clutter]), target, kernel="tukey")
    assert np.linalg.norm(pose_error(res.T, T_true)[:3]) < 5e-3
    assert res.fitness < 0.9


def test_covariance_matches_monte_carlo_scatter(target: np.ndarray) -> None:
    """The reported covariance predicts the scatter of repeated registrations."""
    tgt = prepare_target(target)
    T_true = perturb(np.eye(4), [0.05, 0.0, 0.0, 0.0, 0.0, 0.02])
    rng = np.random.default_rng(11)
    clean = apply_T(inv_T(T_true), target[::3])
    errs, sds = [], []
    for _ in range(12):
        src = clean + rng.normal(0, 0.01, clean.shape)
        res = icp(src, tgt, max_correspondence_distance=(0.3, 0.1), kernel="none")
        errs.append(pose_error(res.T, T_true))
        sds.append(np.sqrt(np.diag(res.covariance)))
    ratio = np.std(errs, axis=0) / np.mean(sds, axis=0)
    assert np.all(ratio > 0.3) and np.all(ratio < 3.0), ratio


def test_blocked_covariance_covers_errors_shared_within_blocks(target: np.ndarray) -> None:
    """Errors shared by the points of a patch do not average out; the blocked sandwich
    predicts their scatter, the per-point one (independent residuals) does not."""
    tgt = prepare_target(target)
    T_true = perturb(np.eye(4), [0.05, 0.0, 0.0, 0.0, 0.0, 0.02])
    rng = np.random.default_rng(12)
    clean = target[::3]
    normals = tgt.normals[::3]
    _, cell = np.unique(np.floor(clean / 1.0).astype(int), axis=0, return_inverse=True)
    cell = cell.ravel()
    errs, sd_point, sd_block = [], [], []
    for _ in range(16):
        # 2 mm shared by each 1 m patch along its normal, 2 mm independent noise
        shift = rng.normal(0, 0.002, cell.max() + 1)[cell, None] * normals
        src = apply_T(inv_T(T_true), clean + shift + rng.normal(0, 0.002, clean.shape))
        for block, out in ((None, sd_point), (1.0, sd_block)):
            res = icp(src, tgt, max_correspondence_distance=(0.3, 0.1), covariance_block=block)
            out.append(np.sqrt(np.diag(res.covariance)))
        errs.append(pose_error(res.T, T_true))
    rms = np.sqrt(np.mean(np.square(errs), axis=0))
    ratio_point = rms / np.sqrt(np.mean(np.square(sd_point), axis=0))
    ratio_block = rms / np.sqrt(np.mean(np.square(sd_block), axis=0))
    assert np.all(ratio_block > 0.6) and np.all(ratio_block < 1.6), ratio_block
    assert np.all(ratio_point > 1.8), ratio_point


def test_weakest_direction_of_a_corridor() -> None:
    """Floor and two long walls along x: nothing holds the translation along x."""
    rng = np.random.default_rng(8)
    n = 4000
    floor = np.c_[rng.uniform(-10, 10, n), rng.uniform(-1.5, 1.5, n), np.zeros(n)]
    walls = np.c_[rng.uniform(-10, 10, n), rng.choice([-1.5, 1.5], n), rng.uniform(0, 3, n)]
    corridor = np.vstack([floor, walls])
    # exact normals (PCA normals where floor meets wall would lean along x)
    normals = np.vstack(
        [
            np.tile([0.0, 0.0, 1.0], (n, 1)),
            np.c_[0 * walls[:, :1], -np.sign(walls[:, 1:2]), 0 * walls[:, :1]],
        ]
    )
    tgt = prepare_target(corridor, normals)
    src = corridor[::4] + rng.normal(0, 0.003, corridor[::4].shape)
    res = icp(src, tgt, init=perturb(np.eye(4), [0.0, 0.02, 0.0, 0.0, 0.0, 0.01]))
    weak = weakest_direction(res.information)
    assert weak.label == "translation x" and abs(weak.vector[0]) > 0.99
    assert weak.translation_share > 0.99 and weak.sigma > 1.0
    assert res.condition < 1e-6
    np.testing.assert_allclose(np.linalg.norm(weak.vector), 1.0)


def test_weakest_direction_of_a_room(target: np.ndarray) -> None:
    T_true = perturb(np.eye(4), [0.05, 0.0, 0.0, 0.0, 0.0, 0.02])
    res = icp(make_source(9, T_true), target)
    weak = weakest_direction(res.information)
    assert weak.sigma < 0.002 and weak.condition > 1e-3
    assert 1.0 < weak.lever < 5.0  # the RMS lever arm of a 6 x 4 x 3 m room
    # heading held least: the weakest direction is a pure rotation about z, its sigma
    # the displacement at the lever arm, lever * 1 rad / sqrt(1)
    info = np.diag([1e6, 1e6, 1e6, 1e3, 1e3, 1.0])
    w = weakest_direction(info)
    assert w.label == "rotation about z (heading)" and w.translation_share < 1e-12
    np.testing.assert_allclose(w.lever, np.sqrt(2001.0 / 3e6))
    np.testing.assert_allclose(w.sigma, w.lever)


def test_prepared_target_reused(target: np.ndarray) -> None:
    tgt = prepare_target(target)
    T_true = perturb(np.eye(4), [0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
    a = icp(make_source(1, T_true), tgt)
    b = icp(make_source(1, T_true), target)
    np.testing.assert_allclose(a.T, b.T, atol=1e-9)


def test_degenerate_plane_reports_low_condition() -> None:
    rng = np.random.default_rng(4)
    plane = np.c_[rng.uniform(0, 5, (2000, 2)), np.zeros(2000)]
    res = icp(plane[::2] + np.array([0.01, 0.0, 0.0]), plane)
    assert res.condition < 1e-6


def test_bad_inputs() -> None:
    pts = np.random.default_rng(0).uniform(0, 1, (100, 3))
    with pytest.raises(InputError, match="method"):
        icp(pts, pts, method="plane")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="kernel"):
        icp(pts, pts, kernel="l1")  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        icp(pts[:, :2], pts)
    with pytest.raises(InputError, match="positive"):
        icp(pts, pts, max_correspondence_distance=-1.0)
