"""``fabflow localize uwb``: files in, base pose out; bad files get a line number."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT
from typer.testing import CliRunner

from fabflow.cli import app
from fabflow.errors import InputError
from fabflow.localize.site import anchors_world
from fabflow.localize.uwb_files import load_anchors_file, localize_from_files
from fabflow.localize.uwb_static import static_fix
from fabflow.positioning.result import BasePose
from fabflow.positioning.uwb_io import (
    read_imu_csv,
    read_ranges_csv,
    write_imu_csv,
    write_ranges_csv,
)
from fabflow.positioning.uwb_platform import heading_from_motion, locate_platform
from fabflow.sensors.uwb import UwbErrorModel, ranging_schedule, simulate_ranges

DATA = ROOT / "tests" / "data" / "uwb"
STATIC = DATA / "static"
MOVING = DATA / "moving"
IDS = ["A1", "A2", "A3", "A4"]


def _truth_static() -> np.ndarray:
    # tests/data/uwb/generate.py: platform at (1.6, 2.2), heading 30 deg; base at (0.3, 0, 0.6)
    yaw = np.radians(30.0)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([1.6, 2.2, 0.0]) + np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ [0.3, 0, 0.6]


def test_static_end_to_end(cli, tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = cli(
        "localize",
        "uwb",
        str(STATIC / "ranges.csv"),
        "--anchors",
        str(STATIC / "anchors.yaml"),
        "-o",
        str(out),
    )
    assert result.returncode == 0, result.stderr
    pose = BasePose.from_dict(json.loads((out / "base_pose.json").read_text()))
    err = pose.T_world_base[:3, 3] - _truth_static()
    sd = np.sqrt(np.diag(pose.covariance))
    assert np.all(np.abs(err) < 4 * sd[:3])
    yaw = np.arctan2(pose.T_world_base[1, 0], pose.T_world_base[0, 0])
    assert abs(yaw - np.radians(30.0)) < 4 * sd[5]
    assert pose.quality["unobserved"] == ["rx", "ry"]
    assert pose.residuals.shape[1] == 1 and pose.rmse > 0


def test_moving_with_imu_in_process(tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = CliRunner().invoke(
        app,
        [
            "localize",
            "uwb",
            str(MOVING / "ranges.csv"),
            "--anchors",
            str(MOVING / "anchors.yaml"),
            "--imu",
            str(MOVING / "imu.csv"),
            "-o",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    pose = BasePose.from_dict(json.loads((out / "base_pose.json").read_text()))
    # generate.py: a 1.5 m line ending at (2.7, 1.5) at height 2.0, heading 0
    expected = np.array([2.7 + 0.3, 1.5, 2.6])
    assert np.linalg.norm(pose.T_world_base[:3, 3] - expected) < 0.08
    yaw = np.arctan2(pose.T_world_base[1, 0], pose.T_world_base[0, 0])
    assert abs(yaw) < np.radians(10.0)
    assert pose.quality["estimator"] == "eskf"
    assert pose.quality["n_rejected_gate"] > 0
    assert pose.integrity is not None and pose.integrity.status == "ok"
    assert "integrity" in result.output


def test_bad_csv_exits_2_with_line_number(cli, tmp_path: Path) -> None:
    bad = tmp_path / "ranges.csv"
    bad.write_text("t,anchor,range\n0.0,A1,3.0\n0.1,A7,3.1\n")
    out = tmp_path / "out"
    result = cli(
        "localize", "uwb", str(bad), "--anchors", str(STATIC / "anchors.yaml"), "-o", str(out)
    )
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert "line 3" in result.stderr and "A7" in result.stderr
    assert not out.exists()


@pytest.mark.parametrize(
    ("text", "where", "what"),
    [
        ("time,anchor,range\n0,A1,3\n", "line 1", "missing column"),
        ("t,anchor,range\n0.0,A1,3.0\n0.2,A2,3.0\n0.1,A3,3.0\n", "line 4", "not sorted"),
        ("t,anchor,range\n0.0,A1,3.0\n0.0,A1,3.1\n", "line 3", "duplicate"),
        ("t,anchor,range\n0.0,A1,3.0\n0.1,B2,3.0\n", "line 3", "unknown anchor"),
        ("t,anchor,range\n0.0,A1,abc\n", "line 2", "not a number"),
        ("t,anchor,range\n0.0,A1,-3\n", "line 2", "negative"),
        ("t,anchor,range,tag\n0.0,A1,3,2\n", "line 2", "tag"),
        ("t,anchor,range\n0.0,A1\n", "line 2", "expected 3 values"),
        ("t,anchor,range\n", None, "no ranges"),
    ],
)
def test_read_ranges_errors(tmp_path: Path, text: str, where: str | None, what: str) -> None:
    path = tmp_path / "r.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=what) as exc:
        read_ranges_csv(path, IDS, n_tags=2)
    assert str(path) in str(exc.value)
    if where is not None:
        assert exc.value.location == where


def test_same_time_different_anchors_is_not_a_duplicate(tmp_path: Path) -> None:
    path = tmp_path / "r.csv"
    path.write_text("t,tag,anchor,range\n0.0,0,A1,3.0\n0.0,0,A2,3.1\n0.0,1,A1,3.2\n")
    log = read_ranges_csv(path, IDS, n_tags=2)
    np.testing.assert_array_equal(log.tag, [0, 0, 1])
    ep = log.epochs(2, 4)
    assert ep.shape == (1, 2, 4) and ep[0, 1, 0] == 3.2


@pytest.mark.parametrize(
    ("text", "what"),
    [
        ("t,ax,ay,az,gx,gy\n0,0,0,9.8,0,0\n", "missing column"),
        ("t,ax,ay,az,gx,gy,gz\n0,0,0,9.8,0,0,0\n0,0,0,9.8,0,0,0\n", "duplicate"),
        ("t,ax,ay,az,gx,gy,gz\n0.1,0,0,9.8,0,0,0\n0.0,0,0,9.8,0,0,0\n", "not sorted"),
        ("t,ax,ay,az,gx,gy,gz\n0.1,0,0,9.8,0,0,0\n", "at least two"),
    ],
)
def test_read_imu_errors(tmp_path: Path, text: str, what: str) -> None:
    path = tmp_path / "imu.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=what):
        read_imu_csv(path)


def test_bad_anchors_file_and_single_tag_without_imu(tmp_path: Path) -> None:
    anchors = tmp_path / "anchors.yaml"
    anchors.write_text("anchors: {A1: [0, 0, 1], A2: [4, 0, 1]}\n")
    runner = CliRunner()
    res = runner.invoke(
        app,
        [
            "localize",
            "uwb",
            str(STATIC / "ranges.csv"),
            "--anchors",
            str(anchors),
            "-o",
            str(tmp_path / "o"),
        ],
    )
    assert res.exit_code == 2 and "anchors" in res.output
    res = runner.invoke(
        app,
        [
            "localize",
            "uwb",
            str(MOVING / "ranges.csv"),
            "--anchors",
            str(MOVING / "anchors.yaml"),
            "-o",
            str(tmp_path / "o"),
        ],
    )
    assert res.exit_code == 2 and "heading" in res.output


def test_heading_from_motion() -> None:
    rng = np.random.default_rng(0)
    t = np.linspace(0, 10, 600)
    xy = np.where(
        t[:, None] < 3, 0.0, (t[:, None] - 3) * 0.3 * np.array([[np.cos(0.5), np.sin(0.5)]])
    )
    xy = xy + 0.05 * rng.standard_normal(xy.shape)
    assert abs(heading_from_motion(xy) - 0.5) < 0.15


# generate.py: the platform ends at (2.7, 1.5) at height 2.0, heading 0; base at +(0.3, 0, 0.6)
MOVING_BASE = np.array([3.0, 1.5, 2.6])


@pytest.fixture(scope="module")
def moving():
    return read_ranges_csv(MOVING / "ranges.csv", IDS, 1), read_imu_csv(MOVING / "imu.csv")


def _localize(tmp_path: Path, moving, ranges=None, accel=None, gyro=None) -> BasePose:
    log, (t, a, g) = moving
    r_path = write_ranges_csv(
        tmp_path / "ranges.csv",
        log.t,
        log.tag,
        log.anchor,
        log.range if ranges is None else ranges,
        IDS,
    )
    imu = write_imu_csv(
        tmp_path / "imu.csv", t, a if accel is None else accel, g if gyro is None else gyro
    )
    return localize_from_files(r_path, MOVING / "anchors.yaml", imu)


def test_consistent_run_has_integrity_ok_and_nis_near_one() -> None:
    pose = localize_from_files(MOVING / "ranges.csv", MOVING / "anchors.yaml", MOVING / "imu.csv")
    integrity = pose.integrity
    assert integrity is not None and integrity.status == "ok" and integrity.reason == ""
    c = integrity.checks
    assert c["n_updates"] + c["n_gated"] == 2280
    assert 0.8 < c["nis_mean"] < 1.2  # measured 0.95 (truncated chi-square(1): 0.97)
    assert 0.8 < c["nis_mean_window"] < c["nis_threshold_window"]
    assert c["window_s"] == 2.0 and c["gated_share_window"] < 0.05
    assert c["gyro_at_rest"]["at_rest"]
    assert integrity.global_test["passed"] and integrity.w_test["passed"]
    # the tests' protection level bounds the actual error, which is within the covariance
    err = pose.T_world_base[:3, 3] - MOVING_BASE
    sd = np.sqrt(np.diag(pose.covariance)[:3])
    assert np.all(np.abs(err) < 4 * sd)
    assert np.hypot(*err[:2]) < integrity.protection_level["horizontal"]
    assert abs(err[2]) < integrity.protection_level["vertical"]
    again = BasePose.from_dict(json.loads(json.dumps(pose.to_dict())))
    assert again.integrity is not None and again.integrity.checks == json.loads(json.dumps(c))


@pytest.mark.parametrize(
    ("fault", "expect"),
    [
        # a bias the filter half absorbs (0.4 m off at the end): the w-test names the anchor
        ({"anchor": 2, "offset": 0.2}, "anchor A3"),
        # two anchors, far off: the gate rejects half the ranges
        ({"anchor": (2, 3), "offset": 1.0}, "gate rejected"),
        # a gyro bias 20 times the model's: the heading turns while standing still
        ({"gyro_z": 0.1}, "gyro"),
        # an accelerometer bias far beyond the model: the filter leaves its ranges behind
        ({"accel_x": 10.0}, "gate rejected"),
    ],
)
def test_faults_fail_the_integrity(tmp_path: Path, moving, fault: dict, expect: str) -> None:
    log, (_, a, g) = moving
    ranges = log.range.copy()
    if "offset" in fault:
        late = (log.t > log.t[-1] - 3.0) & np.isin(log.anchor, fault["anchor"])
        ranges[late] += fault["offset"]
    gyro = g + np.array([0.0, 0.0, fault.get("gyro_z", 0.0)])
    accel = a + np.array([fault.get("accel_x", 0.0), 0.0, 0.0])
    pose = _localize(tmp_path, moving, ranges, accel, gyro)
    assert pose.integrity is not None and pose.integrity.failed
    assert expect in pose.integrity.reason


def test_a_blocked_anchor_is_gated_and_the_pose_holds(tmp_path: Path, moving) -> None:
    log, _ = moving
    late = (log.t > log.t[-1] - 3.0) & (log.anchor == 2)
    pose = _localize(tmp_path, moving, log.range + 1.0 * late)
    integrity = pose.integrity
    assert integrity is not None and integrity.status == "ok"
    assert 0.2 < integrity.checks["gated_share_window"] < 0.5  # one anchor of four
    err = pose.T_world_base[:3, 3] - MOVING_BASE
    assert np.all(np.abs(err) < 4 * np.sqrt(np.diag(pose.covariance)[:3]))


@pytest.mark.parametrize(
    ("change", "line", "what"),
    [
        ("value", "line 102", "specific force"),
        ("gap", "line 402", "gap of 1e\\+09 s"),
        ("shift", None, "does not cover the ranges"),
        ("late", None, "does not cover the ranges"),
    ],
)
def test_impossible_imu_records_are_refused(
    tmp_path: Path, moving, change: str, line: str | None, what: str
) -> None:
    _, (t, a, g) = moving
    t, a = t.copy(), a.copy()
    if change == "value":
        a[100, 0] = 1e308
    elif change == "gap":
        t[400:] += 1e9
    elif change == "shift":
        t += 100.0  # another run's record
    else:
        t = t[: t.size // 2]  # stops halfway through the ranges
        a, g = a[: t.size], g[: t.size]
    imu = write_imu_csv(tmp_path / "imu.csv", t, a, g)
    with pytest.raises(InputError, match=what) as exc:
        localize_from_files(MOVING / "ranges.csv", MOVING / "anchors.yaml", imu)
    assert exc.value.source == str(imu) and exc.value.location == line


def test_impossible_imu_exits_2_without_traceback(cli, tmp_path: Path) -> None:
    imu = tmp_path / "imu.csv"
    imu.write_text("t,ax,ay,az,gx,gy,gz\n0,0,0,9.8,0,0,0\n0.01,1e308,0,9.8,0,0,0\n")
    out = tmp_path / "out"
    result = cli(
        "localize",
        "uwb",
        str(MOVING / "ranges.csv"),
        "--anchors",
        str(MOVING / "anchors.yaml"),
        "--imu",
        str(imu),
        "-o",
        str(out),
    )
    assert result.returncode == 2
    assert "Traceback" not in result.stderr and "line 3" in result.stderr
    assert not out.exists()


def _blocked_site(tmp_path: Path, seed: int) -> tuple[Path, Path, np.ndarray]:
    """A 12 m site whose anchor A1 the structure hides from both tags: 5 s of ranges
    (no calibration error), the anchors file, and the platform's x, y."""
    anchors = np.array([[0.0, 0.0, 1.0], [12.0, 0.0, 1.0], [12.0, 12.0, 1.0], [0.0, 12.0, 3.2]])
    tags = np.array([[0.8, 0.0, 1.5], [-0.8, 0.0, 1.5]])
    yaw = np.radians(30.0)
    c, s = np.cos(yaw), np.sin(yaw)
    platform = np.array([9.0, 9.0, 0.0])
    tags_w = platform + tags @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    t, ti, ai = ranging_schedule(5.0, 60.0, 4, n_tags=2)
    occluded = np.zeros((2, 4), dtype=bool)
    occluded[:, 0] = True
    # a noisy chip (5 cm, growing 1 cm/m): its cleaning window reaches into the excess
    noisy = UwbErrorModel(sigma_1m=0.05, growth=0.01)
    sim = simulate_ranges(
        anchors, tags_w[ti], noisy, np.random.default_rng(seed), occluded=occluded[ti]
    )
    r = np.take_along_axis(sim.ranges, ai[..., None], axis=-1)[..., 0]
    ranges = tmp_path / "ranges.csv"
    write_ranges_csv(ranges, t.ravel(), ti.ravel(), ai.ravel(), r.ravel(), IDS)
    doc = {
        "anchors": {k: a.tolist() for k, a in zip(IDS, anchors, strict=True)},
        "sigma": 0.05,
        "sigma_growth": 0.01,
        "multipath_sigma": 0.0,
        "tags": tags.tolist(),
        "calibration": {k: [0.0, 1.0] for k in IDS},
    }
    (tmp_path / "anchors.yaml").write_text(json.dumps(doc), encoding="utf-8")  # YAML too
    return ranges, tmp_path / "anchors.yaml", platform[:2]


def test_measured_files_get_the_estimate_of_a_simulated_station(tmp_path: Path) -> None:
    # half the ranges of A1's long links carry an NLOS excess (0.3-1.5 m); those the
    # cleaning keeps bias the links long. The file's estimate is static_fix's, which
    # takes them off, and nearer the truth than the same fix without the correction
    corrected, plain = [], []
    for seed in range(6):
        folder = tmp_path / str(seed)
        folder.mkdir()
        ranges, anchors_yaml, truth = _blocked_site(folder, seed)
        pose = localize_from_files(ranges, anchors_yaml)
        setup, T_platform_base = load_anchors_file(anchors_yaml)
        model = setup.error_model()
        _, A = anchors_world(setup)
        tags = np.asarray(setup.tags, dtype=float)
        epochs = read_ranges_csv(ranges, IDS, 2).epochs(2, 4)
        bias_sigma = np.full(4, setup.calibration_sigma)
        fix, rej = static_fix(model, A, epochs, tags, model.field_sigma, bias_sigma)
        np.testing.assert_allclose(pose.T_world_base, fix.T @ T_platform_base, atol=1e-12)
        uncorrected = locate_platform(
            A, rej.ranges, tags, model.sigma, anchor_bias_sigma=bias_sigma,
            link_sigma=model.field_sigma,
        )  # fmt: skip
        corrected.append(np.hypot(*(fix.T[:2, 3] - truth)))
        plain.append(np.hypot(*(uncorrected.T[:2, 3] - truth)))
    assert np.mean(corrected) < 0.8 * np.mean(plain), (corrected, plain)
