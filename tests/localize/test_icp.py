"""Scan-to-map localization on the simulated site, map building, station and CLI."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from helpers import ROOT
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.design.elements import Element
from fabflow.errors import InputError, LocalizationError
from fabflow.localize.icp import COARSE_REACH, coarse_schedule, localize_station
from fabflow.localize.methods import localizer_arguments
from fabflow.localize.plan import parked_pose
from fabflow.localize.report import parse_numbers
from fabflow.positioning import scan_matching
from fabflow.positioning.pointcloud_io import write_point_cloud
from fabflow.positioning.result import BasePose
from fabflow.positioning.scan_map import ScanMap, build_map, map_from_points
from fabflow.positioning.scan_matching import localize_scan, scan_integrity, to_base_pose
from fabflow.project import IcpSetup, Project, load_project, parse_project
from fabflow.sensors.lidar import LidarModel, simulate_scan
from fabflow.sensors.site_map import mapping_poses, simulated_site_map
from fabflow.sensors.site_scene import site_scene
from fabflow.sim.run import prepare_study, run_seed
from fabflow.transforms.se3 import apply_T, inv_T, make_T, perturb, pose_error
from fabflow.transforms.so3 import exp_so3

MAP_MODEL = LidarModel(n_beams=32, horizontal_resolution_deg=1.0)


@pytest.fixture(scope="module")
def site_map() -> ScanMap:
    # the same cache entry localize_station uses for a project without obstacles
    return simulated_site_map((), 0.03)


def lidar_pose(x: float, y: float, yaw_deg: float, z: float = 1.8) -> np.ndarray:
    return make_T(exp_so3([0.0, 0.0, np.radians(yaw_deg)]), [x, y, z])


def cabin_wall_blocks(n_layers: int) -> list[Element]:
    """A U of blocks (x 0..4, y 0..3.3) standing in for a half-built cabin."""
    out = []
    for layer in range(n_layers):
        z = 0.0525 + 0.105 * layer
        for i in range(6):
            for x, y, yaw in ((0.35 + 0.65 * i, 0.05, 0.0), (0.35 + 0.65 * i, 3.25, 0.0)):
                out.append((x, y, yaw, z))
        for j in range(5):
            out.append((0.05, 0.35 + 0.65 * j, np.pi / 2, z))
    return [
        Element(
            id=f"B{k}",
            type="block",
            T_world_element=make_T(exp_so3([0, 0, yaw]), [x, y, z]),
            layer=round((z - 0.0525) / 0.105),
            extents=np.array([0.6, 0.105, 0.105]),
        )
        for k, (x, y, yaw, z) in enumerate(out)
    ]


@pytest.mark.parametrize(
    "pose,init_error",
    [
        ((6.5, 1.0, 30.0), (0.35, -0.35, 0.0, 0.0, 0.0, np.radians(10.0))),
        ((-2.0, 2.5, -120.0), (-0.5, 0.0, 0.0, 0.0, 0.0, np.radians(-10.0))),
        ((2.0, -3.0, 80.0), (0.0, 0.5, 0.0, 0.0, 0.0, np.radians(7.0))),
    ],
)
def test_localizes_from_half_metre_and_ten_degrees(
    site_map: ScanMap, pose: tuple[float, float, float], init_error: tuple[float, ...]
) -> None:
    T_true = lidar_pose(*pose)
    scene = site_scene(built=cabin_wall_blocks(12))
    scan = simulate_scan(scene, T_true, np.random.default_rng(1))
    loc = localize_scan(scan.points, site_map, perturb(T_true, init_error))
    err = pose_error(loc.T_world_lidar, T_true)
    assert np.linalg.norm(err[:3]) < 0.005, err
    assert abs(np.degrees(err[5])) < 0.1
    assert loc.icp.fitness > 0.5 and loc.structure_fitness > 0.5
    assert loc.icp.inlier_rmse < 0.02
    sd = np.sqrt(np.diag(loc.covariance))
    assert np.all(sd > 0) and sd[0] < 0.005
    assert loc.integrity.status == "ok" and loc.integrity.reason == ""


def test_fails_loudly_instead_of_silently_wrong(site_map: ScanMap) -> None:
    T_true = lidar_pose(6.5, 1.0, 30.0)
    scan = simulate_scan(site_scene(), T_true, np.random.default_rng(2))
    # from 8 m and 115 deg off, ICP converges somewhere: returned, but failed
    far = localize_scan(scan.points, site_map, perturb(T_true, [6.0, -5.0, 0, 0, 0, 2.0]))
    assert np.linalg.norm(pose_error(far.T_world_lidar, T_true)[:3]) > 0.1
    assert far.integrity.failed
    assert re.search(r"fitness|walls", far.integrity.reason)
    assert far.integrity.checks["structure_fitness"] < 0.5
    # only the ground in view (sensor high above an empty plane): failed
    flat = site_scene(built=(), landmarks=None, obstacles=[((-30, -30, -0.1), (30, 30, 0.0))])
    ground = simulate_scan(flat, T_true, np.random.default_rng(3))
    loc = localize_scan(ground.points, site_map, T_true)
    assert loc.integrity.failed
    assert {"structure_fitness", "condition", "weakest_sigma"} & set(
        loc.integrity.checks["failed_checks"]
    )
    # no pose at all: still an error
    with pytest.raises(LocalizationError, match="points after voxelizing"):
        localize_scan(ground.points[:50], site_map, T_true)


def test_rejects_a_match_held_only_by_the_ground(site_map: ScanMap) -> None:
    T_true = lidar_pose(6.5, 1.0, 30.0)
    scan = simulate_scan(site_scene(), T_true, np.random.default_rng(4))
    wrong = perturb(T_true, [0.8, 0.0, 0.0, 0.0, 0.0, 0.15])
    loc = localize_scan(
        scan.points,
        site_map,
        wrong,
        coarse_schedule=None,
        fine_schedule=(0.05,),
        min_fitness=0.1,
    )
    assert loc.integrity.failed and "walls" in loc.integrity.reason
    assert "(required 50%)" in loc.integrity.reason
    assert loc.integrity.checks["failed_checks"] == ["structure_fitness"]
    assert loc.integrity.checks["structure_fitness"] < 0.5
    # the base pose carries the failure
    pose = to_base_pose(loc, np.eye(4))
    assert pose.integrity is loc.integrity and pose.integrity.failed


def scene_map(boxes: list[tuple[tuple[float, ...], tuple[float, ...]]]) -> tuple:
    """A scene of boxes only and a 3 cm map of it with exact normals."""
    scene = site_scene(landmarks=None, obstacles=boxes)
    pts, face = trimesh.sample.sample_surface(scene, 400_000, seed=0)
    return scene, map_from_points(np.asarray(pts), 0.03, scene.face_normals[face])


@pytest.mark.parametrize(
    "name,boxes,direction",
    [
        ("flat ground", [((-30, -30, -0.1), (30, 30, 0.0))], r"translation [xy]|rotation about z"),
        (
            "corridor along x",
            [
                ((-40, -2, -0.1), (40, 2, 0.0)),
                ((-40, -2.2, 0), (40, -2.0, 3.0)),
                ((-40, 2.0, 0), (40, 2.2, 3.0)),
            ],
            r"translation x",
        ),
    ],
)
def test_degenerate_geometry_fails_naming_the_direction(
    name: str, boxes: list, direction: str
) -> None:
    scene, scan_map = scene_map(boxes)
    T_true = lidar_pose(0.5, 0.2, 30.0)
    scan = simulate_scan(scene, T_true, np.random.default_rng(3))
    loc = localize_scan(scan.points, scan_map, perturb(T_true, [0.02, -0.01, 0, 0, 0, 0.005]))
    integrity = loc.integrity
    assert integrity.failed, name
    assert "condition" in integrity.checks["failed_checks"]
    assert re.search(rf"does not constrain ({direction})", integrity.reason), integrity.reason
    assert re.match(direction, integrity.checks["weakest_axis"])
    assert integrity.checks["weakest_sigma"] > integrity.checks["max_weakest_sigma"]
    assert abs(np.linalg.norm(integrity.checks["weakest_direction"]) - 1.0) < 1e-9
    if name == "corridor along x":
        assert (
            abs(loc.weakest.vector[0]) > 0.99 and integrity.checks["unconstrained_directions"] == 1
        )
    else:
        assert integrity.checks["unconstrained_directions"] == 3


def test_build_map_registers_scans_from_odometry_guesses() -> None:
    scene = site_scene()
    rng = np.random.default_rng(5)
    poses = mapping_poses()[:4]
    scans = [simulate_scan(scene, T, rng, MAP_MODEL).points for T in poses]
    guesses = [poses[0]] + [perturb(T, [0.1, -0.08, 0.0, 0.0, 0.0, 0.03]) for T in poses[1:]]
    built = build_map(scans, guesses, voxel_size=0.05)
    for T_est, T_true in zip(built.T_world_scans, poses, strict=True):
        err = pose_error(T_est, T_true)
        assert np.linalg.norm(err[:3]) < 0.01 and abs(err[5]) < 0.002
    assert len(built.coarse) < len(built)
    with pytest.raises(InputError):
        build_map(scans, guesses[:2])


def test_base_pose_covariance_moves_to_the_base(site_map: ScanMap) -> None:
    T_true = lidar_pose(6.5, 1.0, 30.0)
    scan = simulate_scan(site_scene(), T_true, np.random.default_rng(6))
    loc = localize_scan(scan.points, site_map, T_true)
    T_base_lidar = make_T(np.eye(3), [0.9, 0.0, 0.6])
    pose = to_base_pose(loc, T_base_lidar, station="S1")
    np.testing.assert_allclose(pose.T_world_base, loc.T_world_lidar @ inv_T(T_base_lidar))
    assert pose.method == "icp" and pose.station == "S1"
    assert pose.residuals.shape[1] == 1 and len(pose.residuals) <= 1000
    # errors in the world frame: the base moves with the sensor's rotation error about the
    # sensor origin, d_base = d_lidar + r x (t_base - t_lidar)
    a = pose.T_world_base[:3, 3] - loc.T_world_lidar[:3, 3]
    G = np.eye(6)
    G[:3, 3:] = -np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    np.testing.assert_allclose(pose.covariance, G @ loc.covariance @ G.T, rtol=1e-9, atol=1e-15)
    assert json.loads(json.dumps(pose.to_dict()))["quality"]["fitness"] == loc.icp.fitness


def test_clean_scan_integrity_ok(site_map: ScanMap) -> None:
    T_true = lidar_pose(6.5, 1.0, 30.0)
    scan = simulate_scan(site_scene(), T_true, np.random.default_rng(6))
    loc = localize_scan(scan.points, site_map, perturb(T_true, [0.02, 0.01, 0, 0, 0, 0.01]))
    integrity = loc.integrity
    assert integrity.status == "ok" and integrity.reason == ""
    assert integrity.redundancy == loc.icp.n_inliers - 6
    assert integrity.global_test == {}  # no global test for correlated residuals
    c = integrity.checks
    assert c["failed_checks"] == []
    assert c["fitness"] == loc.icp.fitness >= c["min_fitness"]
    assert c["structure_fitness"] == loc.structure_fitness >= c["min_structure_fitness"]
    assert c["inlier_rmse"] == loc.icp.inlier_rmse <= c["max_rmse"]
    assert c["condition"] == loc.icp.condition >= c["min_condition"]
    assert 0 < c["weakest_sigma"] < c["max_weakest_sigma"]
    assert c["weakest_axis"] == loc.weakest.label and len(c["weakest_direction"]) == 6
    # the weakest sigma is the largest sigma of the scaled covariance
    S = np.diag(np.r_[np.ones(3), np.full(3, c["weakest_lever"])])
    top = np.linalg.eigvalsh(S @ loc.covariance @ S)[-1]
    np.testing.assert_allclose(c["weakest_sigma"], np.sqrt(top), rtol=1e-6)
    pose = to_base_pose(loc, make_T(np.eye(3), [0.9, 0.0, 0.6]), station="S1")
    assert pose.integrity is integrity
    back = BasePose.from_dict(json.loads(json.dumps(pose.to_dict())))
    assert back.integrity is not None and back.integrity.status == "ok"
    assert back.integrity.checks["weakest_axis"] == c["weakest_axis"]
    assert c["converged"] and c["iterations"] == loc.icp.iterations
    # the same match, had its iterations run out: not at a minimum, so it fails
    stopped = dataclasses.replace(loc.icp, converged=False)
    limits = {k: c[k] for k in ("min_fitness", "max_rmse", "min_structure_fitness")}
    limits["max_weakest_sigma"] = c["max_weakest_sigma"]
    failed = scan_integrity(stopped, loc.structure_fitness, loc.weakest, limits)
    assert failed.status == "failed" and failed.checks["failed_checks"] == ["converged"]
    assert "did not converge" in failed.reason


def sim_stations(n: int) -> list[tuple[np.ndarray, np.random.Generator]]:
    """Seeded parked poses of the simulation test project (run seeds of ``fabflow simulate``)."""
    project = load_project(ROOT / "tests" / "data" / "sim")
    study = prepare_study(project, "icp")
    out = []
    for run in range(n):
        rng = np.random.default_rng(run_seed(0, run))
        _, T_true = parked_pose(project, study.stations[0], rng)
        out.append((T_true, rng))
    return out


def _consistency(project: Project) -> np.ndarray:
    """RMS error over RMS predicted sigma per axis of 10 seeded ICP stations."""
    study = prepare_study(project, "icp")
    extra = localizer_arguments(project, "icp", study.stations[0])
    errs, sds = [], []
    for T_true, rng in sim_stations(10):
        pose = localize_station(project, T_true, rng, "S1", **extra)
        assert pose.integrity is not None and pose.integrity.status == "ok"
        errs.append(pose_error(pose.T_world_base, T_true))
        sds.append(np.sqrt(np.diag(pose.covariance)))
    rms = np.sqrt(np.mean(np.square(errs), axis=0))
    return rms / np.sqrt(np.mean(np.square(sds), axis=0))


def test_covariance_is_consistent_over_stations() -> None:
    """RMS error over RMS predicted sigma near 1 in x, y and heading (10 stations)."""
    ratio = _consistency(load_project(ROOT / "tests" / "data" / "sim"))
    assert np.all(ratio[[0, 1, 5]] > 0.6) and np.all(ratio[[0, 1, 5]] < 1.6), ratio


def test_covariance_counts_the_channel_range_bias(monkeypatch: pytest.MonkeyPatch) -> None:
    """With a 2 cm range bias per laser channel the fixes err several times more; the
    covariance counts it (x, y, heading consistent), and without that term it would be
    over-confident."""
    project = load_project(ROOT / "tests" / "data" / "sim")
    setup = project.localization.icp or IcpSetup()
    biased = project.model_copy(
        update={
            "localization": project.localization.model_copy(
                update={"icp": setup.model_copy(update={"channel_bias_sigma": 0.02})}
            )
        }
    )
    ratio = _consistency(biased)
    assert np.all(ratio[[0, 1, 5]] > 0.6) and np.all(ratio[[0, 1, 5]] < 1.6), ratio
    real_icp = scan_matching.icp

    def without_the_term(*args: object, **kwargs: object) -> object:
        kwargs["ray_sigma"] = 0.0
        return real_icp(*args, **kwargs)

    monkeypatch.setattr(scan_matching, "icp", without_the_term)
    blind = _consistency(biased)
    assert np.max(blind[[0, 1]]) > 1.6, blind


PROJECT = """
name: icp test
localization:
  method: icp
  icp:
    voxel_size: 0.05
elements:
  - task_points:
      - id: T1
        pose: {xyz: [1, 1, 1]}
simulation:
  driving_error: 0.2
  driving_heading_error_deg: 4.0
"""


def test_localize_station_on_the_simulated_site() -> None:
    project = parse_project(PROJECT)
    T_world_platform = make_T(exp_so3([0, 0, np.radians(-60.0)]), [1.0, 5.5, 0.0])
    T_world_base = T_world_platform @ project.robot.platform.T_platform_base.matrix()
    pose = localize_station(
        project, T_world_base, np.random.default_rng(7), "S2", built=cabin_wall_blocks(6)
    )
    err = pose_error(pose.T_world_base, T_world_base)
    assert np.linalg.norm(err[:3]) < 0.005 and abs(np.degrees(err[5])) < 0.1
    assert pose.station == "S2" and pose.method == "icp"
    assert pose.quality["map"] == "simulated"
    assert pose.integrity is not None and pose.integrity.status == "ok"


def test_parse_init() -> None:
    assert parse_numbers("1, -2.5,30", "--init", "x,y,yaw") == (1.0, -2.5, 30.0)
    for bad in ("1,2", "a,b,c", "1,2,3,4", "1,2,nan"):
        with pytest.raises(InputError, match="--init"):
            parse_numbers(bad, "--init", "x,y,yaw")


def test_cli_localize_icp(tmp_path: Path, cli, site_map: ScanMap) -> None:
    write_point_cloud(tmp_path / "map.ply", site_map.points, site_map.normals)
    T_world_platform = make_T(exp_so3([0, 0, np.radians(30.0)]), [6.0, 1.0, 0.0])
    T_platform_lidar = make_T(np.eye(3), [0.9, 0.0, 1.2])
    T_world_lidar = T_world_platform @ T_platform_lidar
    scan = simulate_scan(site_scene(), T_world_lidar, np.random.default_rng(8))
    write_point_cloud(tmp_path / "scan.ply", scan.points)
    res = cli(
        "localize", "icp", str(tmp_path / "scan.ply"), "--map", str(tmp_path / "map.ply"),
        "--init", "6.3,0.8,25", "-o", str(tmp_path / "out"), "--station", "S1",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    data = json.loads((tmp_path / "out" / "base_pose.json").read_text())
    T_true = T_world_platform @ make_T(np.eye(3), [0.0, 0.0, 0.6])
    err = pose_error(np.array(data["T_world_base"]), T_true)
    assert np.linalg.norm(err[:3]) < 0.005
    assert data["method"] == "icp" and data["station"] == "S1"
    assert np.array(data["covariance"]).shape == (6, 6)
    assert data["integrity"]["status"] == "ok" and "integrity" in res.stdout

    bad = cli(
        "localize", "icp", str(tmp_path / "scan.ply"), "--map", str(tmp_path / "map.ply"),
        "--init", "14,9", "-o", str(tmp_path / "out"),
    )  # fmt: skip
    assert bad.returncode == 2
    assert "--init" in bad.stderr and "Traceback" not in bad.stderr
    # the earlier result is left in place
    assert json.loads((tmp_path / "out" / "base_pose.json").read_text()) == data

    # a pose that fails its checks (far-off start) is written with its tests and exits 2,
    # like every method's failed pose
    failed = cli(
        "localize", "icp", str(tmp_path / "scan.ply"), "--map", str(tmp_path / "map.ply"),
        "--init", "12,-4,140", "-o", str(tmp_path / "out"),
    )  # fmt: skip
    assert failed.returncode == 2 and "Traceback" not in failed.stderr
    assert re.search(r"fitness|walls|correspondences|constrain", failed.stderr)
    assert "do not build from this pose" in failed.stderr
    written = json.loads((tmp_path / "out" / "base_pose.json").read_text())
    assert written["integrity"]["status"] == "failed"
    assert written["integrity"]["reason"] in failed.stderr

    missing = cli(
        "localize", "icp", str(tmp_path / "nope.ply"), "--map", str(tmp_path / "map.ply"),
        "--init", "6,1,30", "-o", str(tmp_path / "o2"),
    )  # fmt: skip
    assert missing.returncode == 2 and "nope.ply" in missing.stderr


def test_scan_points_transform_consistently(site_map: ScanMap) -> None:
    """The scan lands on the map at the true pose (simulator and map agree)."""
    T_true = lidar_pose(0.0, -3.0, 10.0)
    scan = simulate_scan(site_scene(), T_true, np.random.default_rng(9))
    d, _ = site_map.target.tree.query(apply_T(T_true, scan.points), k=1)
    assert np.median(d) < 0.05


@settings(deadline=None, max_examples=50)
@given(
    xy=st.floats(0.0, 1.0),
    yaw_deg=st.floats(0.0, 20.0),
    d=st.floats(0.05, 2.0),
)
def test_the_coarse_stage_reaches_as_far_as_the_parking_can_be_off(
    xy: float, yaw_deg: float, d: float
) -> None:
    setup = IcpSetup(max_correspondence_distance=d)
    first, last = coarse_schedule(setup, (xy, np.radians(yaw_deg)))
    off = 3.0 * (xy + np.radians(yaw_deg) * COARSE_REACH)  # 3 sigma at a typical range
    assert last == d and d <= first <= 4.0 * d
    assert first == pytest.approx(min(max(off, d), 4.0 * d))
    # a guess given by hand: the widest reach
    assert coarse_schedule(setup, None) == (4.0 * d, d)
