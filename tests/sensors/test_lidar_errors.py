"""LiDAR error terms: channel bias, incidence angle, clutter, motion in a scan, and the
ICP covariance's share for the channel bias."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.design.elements import Element
from fabflow.errors import InputError, UnsupportedError
from fabflow.positioning.icp import icp, prepare_target
from fabflow.positioning.lidar_channels import channel_of
from fabflow.positioning.scan_map import transform_map
from fabflow.positioning.scan_matching import localize_scan
from fabflow.sensors.lidar import LidarModel, simulate_scan
from fabflow.sensors.lidar_errors import (
    LidarErrorModel,
    column_poses,
    draw_channel_bias,
    incidence_sigma,
)
from fabflow.sensors.site_map import mapping_poses, simulated_site_map, with_as_built
from fabflow.sensors.site_scene import site_scene
from fabflow.transforms.se3 import apply_T, inv_T, make_T, pose_error
from fabflow.transforms.so3 import exp_so3

EXACT = LidarModel(n_beams=16, horizontal_resolution_deg=2.0, range_sigma=0.0)
ROOM = trimesh.creation.box(extents=(10.0, 8.0, 4.0))


def test_bad_error_models_are_refused() -> None:
    for bad in (
        {"channel_bias_sigma": -0.01},
        {"channel_bias_sigma": float("nan")},
        {"beam_divergence": float("inf")},
        {"clutter_fraction": 1.0},
        {"max_incidence_deg": 0.0},
        {"max_incidence_deg": 91.0},
    ):
        with pytest.raises(InputError):
            LidarErrorModel(**bad)


@settings(max_examples=100, deadline=None)
@given(
    st.floats(0.3, 30.0),
    st.floats(0.0, 89.0),
    st.floats(0.0, 89.0),
    st.floats(0.0, 0.01),
)
def test_incidence_sigma_grows_with_the_angle_and_the_range(
    r: float, a: float, b: float, divergence: float
) -> None:
    lo, hi = sorted((a, b))
    s_lo, s_hi = incidence_sigma([r, r], np.cos(np.radians([lo, hi])), divergence)
    assert 0.0 <= s_lo <= s_hi + 1e-15
    assert incidence_sigma(r, 1.0, divergence) == pytest.approx(0.0, abs=1e-12)
    # the angle the given cosine holds: near normal incidence a float cosine keeps
    # only a few digits of the angle, which no formula of it can give back
    held = np.arccos(np.cos(np.radians(hi)))
    expected = r * divergence * np.tan(held) / np.sqrt(12.0)
    assert s_hi == pytest.approx(expected, rel=1e-6, abs=1e-12)


def test_channel_bias_shifts_every_range_of_its_channel() -> None:
    T = make_T(exp_so3([0.0, 0.0, 0.4]), [0.5, -0.3, 0.2])
    bias = np.linspace(-0.05, 0.05, EXACT.n_beams)
    plain = simulate_scan(ROOM, T, np.random.default_rng(0), EXACT)
    biased = simulate_scan(
        ROOM, T, np.random.default_rng(0), EXACT, LidarErrorModel(), channel_bias=bias
    )
    np.testing.assert_array_equal(plain.ray_index, biased.ray_index)
    beam = plain.ray_index // EXACT.n_columns
    np.testing.assert_allclose(biased.ranges - plain.ranges, bias[beam], atol=1e-12)
    drawn = draw_channel_bias(
        LidarErrorModel(channel_bias_sigma=0.02), 4000, np.random.default_rng(1)
    )
    assert np.std(drawn) == pytest.approx(0.02, rel=0.05)
    assert not draw_channel_bias(LidarErrorModel(), 8, np.random.default_rng(1)).any()


def test_oblique_returns_scatter_more_and_the_most_oblique_are_dropped() -> None:
    T = make_T(np.eye(3), [0.0, 0.0, 0.0])
    errors = LidarErrorModel(beam_divergence=0.01, max_incidence_deg=60.0)
    plain = simulate_scan(ROOM, T, np.random.default_rng(0), EXACT)
    noisy = simulate_scan(ROOM, T, np.random.default_rng(0), EXACT, errors)
    d = EXACT.directions()
    normals = ROOM.face_normals[plain.face_index]
    cos = np.abs(np.einsum("ij,ij->i", normals, d[plain.ray_index]))
    kept = cos >= np.cos(np.radians(60.0)) - 1e-12
    np.testing.assert_array_equal(noisy.ray_index, plain.ray_index[kept])
    dev = np.abs(noisy.ranges - plain.ranges[kept])
    steep = cos[kept] > np.cos(np.radians(20.0))
    assert dev[~steep].mean() > 3 * dev[steep].mean()


def test_clutter_returns_early_in_its_share_of_the_rays() -> None:
    T = make_T(np.eye(3), [0.0, 0.0, 0.0])
    plain = simulate_scan(ROOM, T, np.random.default_rng(0), EXACT)
    cluttered = simulate_scan(
        ROOM, T, np.random.default_rng(0), EXACT, LidarErrorModel(clutter_fraction=0.2)
    )
    short = cluttered.ranges < plain.ranges - 1e-9
    assert short.mean() == pytest.approx(0.2, abs=0.03)
    assert (cluttered.ranges >= EXACT.min_range).all()
    assert not (cluttered.ranges > plain.ranges + 1e-9).any()


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3),
    st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3),
)
def test_column_poses_move_at_the_twist_about_the_stamp(v: list[float], w: list[float]) -> None:
    T = make_T(exp_so3([0.1, -0.2, 0.3]), [1.0, 2.0, 3.0])
    poses = column_poses(T, [*v, *w], 600, 10.0)
    t = (np.arange(600) + 0.5) / 6000.0 - 0.05
    np.testing.assert_allclose(poses[:, :3, 3], T[:3, 3] + t[:, None] * np.asarray(v), atol=1e-12)
    # symmetric about the stamp: the mean position is the stamp's
    np.testing.assert_allclose(poses[:, :3, 3].mean(axis=0), T[:3, 3], atol=1e-12)
    np.testing.assert_allclose(
        poses[:, :3, :3] @ np.swapaxes(poses[:, :3, :3], 1, 2),
        np.eye(3)[None].repeat(600, 0),
        atol=1e-12,
    )


def test_a_moving_scan_is_distorted_by_the_distance_travelled_in_it() -> None:
    T = make_T(np.eye(3), [0.0, 0.0, 0.0])
    v = 1.0  # m/s along x, towards the wall at x = 5
    still = simulate_scan(ROOM, T, np.random.default_rng(0), EXACT)
    moving = simulate_scan(
        ROOM, T, np.random.default_rng(0), EXACT, LidarErrorModel(), twist=[v, 0, 0, 0, 0, 0]
    )
    poses = column_poses(T, [v, 0, 0, 0, 0, 0], EXACT.n_columns, EXACT.rate_hz)
    column = moving.ray_index % EXACT.n_columns
    # each point, put through its own column's pose, lies on the room's walls
    world = np.einsum("nij,nj->ni", poses[column, :3, :3], moving.points) + poses[column, :3, 3]
    gap = np.min(np.abs(np.abs(world) - [5.0, 4.0, 2.0]), axis=1)
    assert gap.max() < 1e-9
    # stacked in one frame the scan is distorted: the first and last columns fired
    # half a revolution's travel (5 cm) off the stamp, the middle ones at it
    same = still.ranges[np.searchsorted(still.ray_index, moving.ray_index)]
    off = np.abs(moving.ranges - same)
    middle = np.isin(column, [EXACT.n_columns // 2 - 1, EXACT.n_columns // 2])
    assert off.max() > 0.04 and off[middle].max() < 1e-3


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1.5, 1.5), min_size=1, max_size=50))
def test_channel_of_is_the_nearest_beam(elevations: list[float]) -> None:
    beams = LidarModel().elevations()
    e = np.asarray(elevations)
    p = np.c_[np.cos(e), np.zeros_like(e), np.sin(e)] * 7.0
    got = channel_of(p, beams)
    best = np.abs(e[:, None] - beams[None]).min(axis=1)
    np.testing.assert_allclose(np.abs(e - beams[got]), best, atol=1e-12)
    with pytest.raises(InputError):
        channel_of(p, beams[::-1])


def test_the_channel_term_only_adds_to_the_icp_covariance() -> None:
    rng = np.random.default_rng(3)
    target = trimesh.sample.sample_surface(ROOM, 20000, seed=1)[0]
    # the sensor 1.5 m off the room's centre: rays start there, not at the origin
    T_sensor = make_T(exp_so3([0.0, 0.0, 0.3]), [1.5, -1.0, 0.4])
    picked = target[rng.choice(len(target), 3000, replace=False)]
    scan = apply_T(inv_T(T_sensor), picked) + rng.normal(0, 0.005, (3000, 3))
    tgt = prepare_target(target)
    groups = channel_of(scan, LidarModel().elevations())
    kwargs = {"init": T_sensor, "max_correspondence_distance": 0.2}
    plain = icp(scan, tgt, **kwargs)
    shared = icp(scan, tgt, **kwargs, ray_groups=groups, ray_sigma=0.02)
    np.testing.assert_array_equal(plain.T, shared.T)
    extra = shared.covariance - plain.covariance
    assert np.linalg.eigvalsh(extra).min() > -1e-12
    assert np.trace(shared.covariance) > 2 * np.trace(plain.covariance)
    # the term by hand: sum over channels of (sum of w J^T n.u) outer itself, sandwiched
    p = apply_T(shared.T, scan)
    d, idx = tgt.tree.query(p, k=1, distance_upper_bound=0.2)
    ok = np.isfinite(d)
    n = tgt.normals[idx[ok]]
    Rs = p[ok] - shared.T[:3, 3]
    u = Rs / np.linalg.norm(Rs, axis=1)[:, None]
    r = np.einsum("ij,ij->i", p[ok] - tgt.points[idx[ok]], n)
    scale = 0.2 / 3.0
    w = np.where(np.abs(r) <= scale, 1.0, scale / np.abs(r))  # Huber, as icp weighs
    J = np.c_[n, np.cross(Rs, n)]
    g = np.stack(
        [
            np.bincount(groups[ok], (J[:, k] * w * np.einsum("ij,ij->i", u, n)), 64)
            for k in range(6)
        ],
        axis=1,
    )
    N_inv = np.linalg.inv((J * w[:, None]).T @ J)
    np.testing.assert_allclose(extra, 0.02**2 * N_inv @ g.T @ g @ N_inv, rtol=1e-6, atol=1e-15)
    with pytest.raises(InputError):
        icp(scan, tgt, ray_groups=groups[:-1], ray_sigma=0.02)
    for bad in (float("nan"), -0.01, 5.0):
        with pytest.raises(InputError):
            icp(scan, tgt, ray_groups=groups, ray_sigma=bad)
    with pytest.raises(UnsupportedError):
        icp(scan, tgt, method="point_to_point", ray_groups=groups, ray_sigma=0.02)


def test_the_map_channel_term_predicts_the_spread_of_map_channel_biases() -> None:
    """A map measured by a biased mapping run: each point moved along the ray it was
    measured on by its channel's bias. Over seeded draws of the biases the fixes of
    one exact scan spread as the ``map_rays`` term predicts."""
    rng = np.random.default_rng(5)
    truth = trimesh.sample.sample_surface(ROOM, 20000, seed=2)[0]
    mapper = np.array([-1.0, 0.5, 0.2])  # where the mapping run's sensor stood
    ray = truth - mapper
    u = ray / np.linalg.norm(ray, axis=1)[:, None]
    elevation = np.arcsin(np.clip(u[:, 2], -1.0, 1.0))
    channel = np.clip(((elevation + 0.6) / 1.2 * 16).astype(np.intp), 0, 15)
    T_sensor = make_T(exp_so3([0.0, 0.0, 0.3]), [1.5, -1.0, 0.4])
    scan = apply_T(inv_T(T_sensor), truth[rng.choice(len(truth), 3000, replace=False)])
    sigma = 0.02
    kwargs = {"init": T_sensor, "max_correspondence_distance": 0.2}
    errors, predicted = [], []
    for _ in range(40):
        bias = rng.normal(0.0, sigma, 16)
        mapped = truth + bias[channel][:, None] * u
        tgt = prepare_target(mapped)
        res = icp(scan, tgt, **kwargs, map_rays=(channel, u, sigma))
        errors.append(pose_error(res.T, T_sensor))
        predicted.append(res.covariance)
    e = np.array(errors)
    C = np.mean(predicted, axis=0)
    ratio = np.sqrt(np.mean(e[:, :3] ** 2, axis=0) / np.diag(C)[:3])
    assert np.all((ratio > 0.6) & (ratio < 1.5)), ratio
    plain = icp(scan, prepare_target(truth), **kwargs)
    assert np.trace(C[:3, :3]) > 10 * np.trace(plain.covariance[:3, :3])
    with pytest.raises(InputError):
        icp(scan, tgt, map_rays=(channel, 2 * u, sigma))
    with pytest.raises(InputError):
        icp(scan, tgt, map_rays=(channel[:-1], u[:-1], sigma))
    with pytest.raises(InputError):
        icp(scan, tgt, map_rays=(channel, u))  # type: ignore[arg-type]
    with pytest.raises(UnsupportedError):
        icp(scan, tgt, method="point_to_point", map_rays=(channel, u, sigma))


def test_bad_scan_inputs_are_refused() -> None:
    T = make_T(np.eye(3), [0.0, 0.0, 0.0])
    with pytest.raises(InputError):
        simulate_scan(ROOM, T, np.random.default_rng(0), EXACT, twist=[1.0, 0.0, 0.0])
    with pytest.raises(InputError):
        simulate_scan(ROOM, T, np.random.default_rng(0), EXACT, twist=[np.nan, 0, 0, 0, 0, 0])
    with pytest.raises(InputError):
        simulate_scan(ROOM, T, np.random.default_rng(0), EXACT, channel_bias=np.zeros(3))
    with pytest.raises(InputError):
        LidarModel(rate_hz=0.0)
    with pytest.raises(InputError):
        channel_of([[np.nan, 0.0, 1.0]], LidarModel().elevations())


def test_a_map_built_by_registration_drifts_by_millimetres() -> None:
    model = LidarModel(n_beams=32, horizontal_resolution_deg=1.0)
    errors = LidarErrorModel(channel_bias_sigma=0.01, beam_divergence=0.003)
    drifting = simulated_site_map(model=model, errors=errors, registered=True)
    perfect = simulated_site_map(model=model, errors=errors)
    true = mapping_poses()
    off = np.array([pose_error(T, Tt) for T, Tt in zip(drifting.T_world_scans, true, strict=True)])
    assert not off[0].any()  # the first scan ties the map to the site
    moved = np.linalg.norm(off[1:, :3], axis=1)
    assert (moved > 1e-4).all() and moved.max() < 0.03
    np.testing.assert_array_equal(np.stack(perfect.T_world_scans), true)
    # the given normals turn with the scans: still unit, and the ground's still up
    np.testing.assert_allclose(np.linalg.norm(drifting.normals, axis=1), 1.0, atol=1e-9)
    ground = drifting.points[:, 2] < 0.02
    assert np.median(np.abs(drifting.normals[ground, 2])) > 0.999


def test_the_map_covariance_predicts_the_drift_of_its_scans() -> None:
    """Over several mapping runs, the RMS of the scans' pose errors against the RMS of
    the sigmas the map reports (its covariance is their average)."""
    model = LidarModel(n_beams=32, horizontal_resolution_deg=1.0)
    errors = LidarErrorModel(beam_divergence=0.003)
    true = mapping_poses()
    err, var = [], []
    for seed in range(5):
        m = simulated_site_map(seed=seed, model=model, errors=errors, registered=True)
        assert m.map_covariance is not None
        err += [pose_error(T, Tt) for T, Tt in zip(m.T_world_scans, true, strict=True)]
        var.append(np.diag(m.map_covariance))
    ratio = np.sqrt(np.mean(np.square(err), axis=0) / np.mean(var, axis=0))
    # (summed along the chain as a random walk it predicted about twice the drift)
    assert np.all((ratio > 0.5) & (ratio < 1.3)), ratio
    assert simulated_site_map(model=model, errors=errors).map_covariance is None


def test_a_map_with_a_covariance_adds_it_to_every_fix() -> None:
    model = LidarModel(n_beams=32, horizontal_resolution_deg=1.0)
    drifting = simulated_site_map(model=model, errors=LidarErrorModel(), registered=True)
    assert drifting.map_covariance is not None
    exact = dataclasses.replace(drifting, map_covariance=None)
    T = make_T(np.eye(3), [2.0, 1.65, 2.5])
    scan = simulate_scan(site_scene(), T, np.random.default_rng(2), model)
    with_map = localize_scan(scan.points, drifting, T, coarse_schedule=None)
    without = localize_scan(scan.points, exact, T, coarse_schedule=None)
    np.testing.assert_array_equal(with_map.T_world_lidar, without.T_world_lidar)
    np.testing.assert_allclose(
        with_map.covariance - without.covariance, drifting.map_covariance, atol=1e-18
    )
    # moved with the map, the covariance turns with it
    R = exp_so3([0.0, 0.0, 0.5])
    moved = transform_map(drifting, make_T(R, [1.0, 2.0, 0.0]))
    R6 = np.kron(np.eye(2), R)
    np.testing.assert_allclose(moved.map_covariance, R6 @ drifting.map_covariance @ R6.T)


def test_blocks_added_to_the_map_carry_their_placement_error_into_the_fix() -> None:
    """The map's as-built blocks are labelled by block; with a placement sigma the
    fix's covariance grows by a positive semi-definite term, the pose stays."""
    model = LidarModel(n_beams=32, horizontal_resolution_deg=1.0)
    base = simulated_site_map(model=model)
    blocks = [
        Element(
            f"B{i}",
            "block",
            make_T(np.eye(3), [1.0 + 0.7 * i, 3.0, 0.3]),
            extents=np.array([0.6, 0.2, 0.6]),
        )
        for i in range(4)
    ]
    plain = with_as_built(base, blocks, np.random.default_rng(1))
    labelled = with_as_built(base, blocks, np.random.default_rng(1), placement_sigma=0.003)
    assert plain.point_groups is None and labelled.group_sigma == 0.003
    groups = labelled.point_groups
    assert groups is not None and set(np.unique(groups)) == {-1, 0, 1, 2, 3}
    # a labelled point lies on its own block (within a voxel)
    on = groups >= 0
    centre = np.array([[1.0 + 0.7 * i, 3.0, 0.3] for i in range(4)])[groups[on]]
    assert (np.abs(labelled.points[on] - centre) <= np.array([0.3, 0.1, 0.3]) + 0.031).all()
    T = make_T(np.eye(3), [2.0, 1.0, 1.2])
    scene = site_scene(built=blocks)
    scan = simulate_scan(scene, T, np.random.default_rng(2), model)
    a = localize_scan(scan.points, plain, T, coarse_schedule=None)
    b = localize_scan(scan.points, labelled, T, coarse_schedule=None)
    np.testing.assert_array_equal(a.T_world_lidar, b.T_world_lidar)
    extra = b.covariance - a.covariance
    assert np.linalg.eigvalsh(extra).min() > -1e-15 and np.trace(extra[:3, :3]) > 0
