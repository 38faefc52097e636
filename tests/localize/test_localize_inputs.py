"""``fabflow localize``: numeric options checked, every file problem named with file and line."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from helpers import DATA, TS_DATA
from typer.testing import CliRunner

from fabflow.cli import app
from fabflow.errors import InputError, LocalizationError
from fabflow.localize import uwb_files
from fabflow.localize.icp import localize_files as localize_icp
from fabflow.localize.report import pose_rows
from fabflow.localize.total_station import localize_files as localize_ts
from fabflow.localize.uwb_files import load_anchors_file, localize_from_files
from fabflow.positioning.pointcloud_io import write_point_cloud
from fabflow.positioning.polar import make_instrument
from fabflow.positioning.total_station import MAX_PRISM_POINTS

STATIC = DATA / "uwb" / "static"
MOVING = DATA / "uwb" / "moving"
TS = ["localize", "total-station", str(TS_DATA / "obs.csv"), "--robot-points"]
TS += [str(TS_DATA / "robot_points.csv")]


@pytest.mark.parametrize(
    "args",
    [
        ["--robot-sigma", "inf"],
        ["--robot-sigma", "-0.001"],
        ["--robot-sigma", "1e200"],
        ["--distance-sigma-mm", "0"],
        ["--angle-sigma-arcsec", "nan"],
        ["--distance-ppm", "-1"],
        ["--instrument-height", "1e9"],
        ["--tcp-xyz", "0,0,100"],
        ["--instrument-abc-deg", "0,0,1e300"],
    ],
)
def test_total_station_options_are_checked(tmp_path: Path, args: list[str]) -> None:
    result = CliRunner().invoke(app, [*TS, *args, "-o", str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    assert f"error: {args[0]}: expected" in " ".join(result.output.split())
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "args", [["--lift", "inf"], ["--init", "1e300,0,0"], ["--init", "1,2,720"]]
)
def test_icp_options_are_checked(tmp_path: Path, args: list[str]) -> None:
    base = ["localize", "icp", "scan.xyz", "--map", "map.ply", "--init", "0,0,0"]
    result = CliRunner().invoke(app, [*base, *args, "-o", str(tmp_path / "out")])
    assert result.exit_code == 2 and f"{args[0]}: expected" in result.output


def test_the_library_checks_the_same_bounds() -> None:
    with pytest.raises(InputError, match="at most 1 metres") as exc:
        localize_ts(TS_DATA / "obs.csv", TS_DATA / "robot_points.csv", robot_sigma=float("inf"))
    assert exc.value.location == "robot_sigma"
    with pytest.raises(InputError) as exc:
        make_instrument("custom", 0.0, 0.0, 1.0)
    assert exc.value.location == "distance_sigma_mm"
    with pytest.raises(InputError) as exc:
        localize_icp("scan.xyz", "map.ply", (0.0, 0.0, float("nan")))
    assert exc.value.location == "init"


def test_total_station_problems_name_the_file(tmp_path: Path) -> None:
    points = tmp_path / "points.csv"
    points.write_text("point_id,x_m,y_m,z_m\nP1,1,0,1\nP2,2,0,1\nP3,3,0,1\nP4,4,0,1\n")
    with pytest.raises(LocalizationError, match="collinear") as exc:
        localize_ts(TS_DATA / "obs.csv", points)
    assert exc.value.source == str(points)
    n = MAX_PRISM_POINTS + 1
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-2, 2, (n, 3))
    points.write_text(
        "point_id,x_m,y_m,z_m\n" + "".join(f"P{k},{x},{y},{z}\n" for k, (x, y, z) in enumerate(xyz))
    )
    obs = tmp_path / "obs.csv"
    obs.write_text(
        "point_id,x_m,y_m,z_m\n"
        + "".join(f"P{k},{x + 5},{y + 5},{z}\n" for k, (x, y, z) in enumerate(xyz))
    )
    with pytest.raises(InputError, match=f"{n} readings match robot points; at most") as exc:
        localize_ts(obs, points)
    assert exc.value.source == str(obs)
    joints = tmp_path / "joints.csv"
    joints.write_text("# prisms\npoint_id,q1_deg,q2_deg\nP1,1,2\nP2,3,4\nP3,5,6\n")
    with pytest.raises(InputError, match="has 6 joints but the file gives 2") as exc:
        localize_ts(TS_DATA / "obs.csv", joints, robot="kuka_kr60_3")
    assert exc.value.source == str(joints) and exc.value.location == "line 2"


def test_uwb_problems_name_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    flat = tmp_path / "flat.yaml"
    flat.write_text("anchors: {A1: [0, 0, 1], A2: [4, 0, 1], A3: [4, 6, 1], A4: [0, 6, 1]}\n")
    with pytest.raises(LocalizationError, match="coplanar") as exc:
        localize_from_files(STATIC / "ranges.csv", flat)
    assert exc.value.source == str(flat)
    monkeypatch.setattr(uwb_files, "MAX_STATIC_RANGES", 100)
    with pytest.raises(InputError, match="more than the 100 of a static") as exc:
        localize_from_files(STATIC / "ranges.csv", STATIC / "anchors.yaml")
    assert exc.value.source == str(STATIC / "ranges.csv")
    monkeypatch.setattr(uwb_files, "MAX_EPOCH_CELLS", 100)
    with pytest.raises(InputError, match="table of epochs") as exc:
        localize_from_files(MOVING / "ranges.csv", MOVING / "anchors.yaml", MOVING / "imu.csv")
    monkeypatch.undo()
    # one tag and an IMU: the heading needs motion, and the ranges of a stand give none
    lines = (STATIC / "ranges.csv").read_text().splitlines()
    ranges = tmp_path / "ranges.csv"
    ranges.write_text("\n".join(x for x in lines if ",1,A" not in x) + "\n")
    anchors = tmp_path / "anchors.yaml"
    text = (STATIC / "anchors.yaml").read_text()
    anchors.write_text(text[: text.index("- - -0.8")] + text[text.index("calibration:") :])
    with pytest.raises(LocalizationError, match="heading") as exc:
        localize_from_files(ranges, anchors, MOVING / "imu.csv")
    assert exc.value.source == str(ranges)


@pytest.mark.parametrize(
    ("text", "where", "what"),
    [
        ("anchors: " + "[" * 5000, "line 1", "nest deeper than"),
        ("anchors: {A1: [0, 0, 1]}\nsigma: 0.1\nsigma: 0.2\n", "line 3", "duplicate key 'sigma'"),
        (
            "anchors: {A1: [0, 0, 1], A2: [4, 0, 1], A3: [4, 6, nan]}\n",
            "line 1",
            "valid number",
        ),  # text, not a number
        ("anchors: {A1: [0, 0, 1], A2: [4, 0, 1], A3: [4, 6, .inf]}\n", "line 1", "not a finite"),
        (
            "anchors: {A1: [0, 0, 1], A2: [4, 0, 1], A3: [4, 6, 1e5]}\n",
            "line 1",
            "beyond the 10000 m",
        ),
        (
            "anchors: {A1: [0, 0, 1], A2: [4, 0, 1], A3: [4, 6, 1]}\ncalibration:\n  A1: [0, 9]\n",
            "line 3",
            "scale 9 is outside",
        ),
        (
            "anchors:\n" + "".join(f"  A{k}: [{k}, 0, 1]\n" for k in range(30)),
            "line 2",
            "more than 24",
        ),
        ("anchors: {A1: [0, 0, 1]}\n", "line 1", "at least 3 anchors"),
        (
            "anchors: {A1: [0, 0, 1], A2: [4, 0, 1], A3: [4, 6, 1]}\nsigma: 2e-6\n",
            "line 2",
            "below 0.0001 m",
        ),
    ],
)
def test_anchors_file_problems_have_their_line(
    tmp_path: Path, text: str, where: str, what: str
) -> None:
    path = tmp_path / "anchors.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=what) as exc:
        load_anchors_file(path)
    assert exc.value.source == str(path) and where in str(exc.value)


def test_anchors_file_is_bounded(tmp_path: Path) -> None:
    path = tmp_path / "anchors.yaml"
    path.write_text("# " + "x" * 70_000 + "\n")
    with pytest.raises(InputError, match=r"more than the 0\.1 MiB"):
        load_anchors_file(path)


def test_a_scan_that_gives_no_pose_is_named(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    u = rng.uniform(0, 1, (3000, 2))
    world = np.c_[u[:, 0] * 10, u[:, 1] * 8, np.zeros(3000)]
    write_point_cloud(tmp_path / "map.ply", world)
    write_point_cloud(tmp_path / "scan.xyz", np.array([[1.0, 2.0, 0.0], [1.0, 2.1, 0.0]]))
    with pytest.raises(LocalizationError) as exc:
        localize_icp(tmp_path / "scan.xyz", tmp_path / "map.ply", (1.0, 1.0, 0.0))
    assert exc.value.source == str(tmp_path / "scan.xyz")


def test_summary_rows_never_print_nan() -> None:
    pose = localize_from_files(STATIC / "ranges.csv", STATIC / "anchors.yaml")
    assert pose.integrity is not None
    odd = dataclasses.replace(
        pose.integrity,
        global_test={"statistic": np.nan, "threshold": np.inf, "passed": False},
        w_test={"max": np.nan, "threshold": None, "passed": False, "suspect": "A1"},
    )
    rows = pose_rows(dataclasses.replace(pose, integrity=odd, rmse=np.nan))
    text = " ".join(value for _, value in rows)
    assert "nan" not in text.lower() and "inf" not in text.replace("info", "")
    assert "n/a" in text
