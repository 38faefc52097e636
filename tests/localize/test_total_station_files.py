"""Total station localization from measured files, and ``fabflow localize total-station``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import TS_DATA
from typer.testing import CliRunner

from fabflow.cli import app
from fabflow.errors import InputError
from fabflow.localize.report import parse_numbers
from fabflow.localize.total_station import localize_files
from fabflow.positioning.polar import GON
from fabflow.positioning.result import BasePose
from fabflow.positioning.ts_io import read_robot_points
from fabflow.transforms.se3 import make_T, pose_error
from fabflow.transforms.so3 import exp_so3

T_TRUE = make_T(exp_so3([0.0, 0.0, np.radians(30.0)]), [6.0, 4.0, 0.5])
"""The base pose the sample readings were generated at (tests/data/total_station/README.md)."""


def test_localize_files_with_instrument_pose() -> None:
    # the same readings with the instrument placed at (1, 2, 0) and turned 90 degrees
    pose = localize_files(
        TS_DATA / "obs.csv",
        TS_DATA / "robot_points.csv",
        instrument_xyz=(1.0, 2.0, 0.0),
        instrument_abc_deg=(90.0, 0.0, 0.0),
        station="S1",
    )
    T_wi = make_T(exp_so3([0, 0, np.pi / 2]), [1.0, 2.0, 0.0])
    err = pose_error(pose.T_world_base, T_wi @ T_TRUE)
    assert np.linalg.norm(err[:3]) < 1e-3
    assert pose.station == "S1" and pose.quality["point_ids"][0] == "P1"
    with pytest.raises(InputError, match="--instrument-xyz"):
        parse_numbers("1,2", "--instrument-xyz", "x,y,z")
    for bad in ((1.0, 2.0), (1.0, float("nan"), 0.0), "1,2,3", (1e400, 0, 0)):
        with pytest.raises(InputError, match="instrument_xyz must be three finite numbers"):
            localize_files(TS_DATA / "obs.csv", TS_DATA / "robot_points.csv", instrument_xyz=bad)
    with pytest.raises(InputError, match="tcp_xyz"):
        localize_files(TS_DATA / "obs.csv", TS_DATA / "robot_points.csv", tcp_xyz=(0.0, 0.0))


def test_robot_points_as_joint_values(tmp_path: Path) -> None:
    from fabflow.positioning.polar import cartesian_to_polar
    from fabflow.robots import get_robot
    from fabflow.transforms.se3 import apply_T

    q_deg = np.array(
        [
            [10, -70, 100, 0, 40, 0],
            [-35, -50, 80, 20, 60, 10],
            [60, -80, 110, -10, 30, 0],
            [0, -40, 60, 0, 70, 45],
            [-70, -65, 95, 5, 45, -20],
        ],
        dtype=float,
    )
    T_flange_prism = make_T(np.eye(3), [0.0, 0.0, 0.2])
    P = (get_robot("kuka_kr60_3").fk(np.radians(q_deg)) @ T_flange_prism)[:, :3, 3]
    hz, v, sd = cartesian_to_polar(apply_T(T_TRUE, P))
    obs = tmp_path / "obs.csv"
    obs.write_text(
        "point_id,hz_gon,v_gon,slope_distance_m\n"
        + "".join(f"J{k},{hz[k] / GON:.6f},{v[k] / GON:.6f},{sd[k]:.5f}\n" for k in range(5))
    )
    pts = tmp_path / "joints.csv"
    pts.write_text(
        "point_id,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n"
        + "".join(f"J{k}," + ",".join(f"{x:g}" for x in q_deg[k]) + "\n" for k in range(5))
    )
    rp = read_robot_points(pts)
    assert rp.xyz is None and rp.joints is not None and rp.joints.shape == (5, 6)
    pose = localize_files(obs, pts, robot="kuka_kr60_3", tcp_xyz=(0.0, 0.0, 0.2))
    assert np.linalg.norm(pose_error(pose.T_world_base, T_TRUE)[:3]) < 2e-4
    with pytest.raises(InputError, match="name the robot"):
        localize_files(obs, pts)
    with pytest.raises(InputError, match="has 5 joints but the file gives 6"):
        localize_files(obs, pts, robot="brokk_170")
    far = tmp_path / "far.csv"
    far.write_text(pts.read_text().replace("J2,60,", "J2,200,"))
    with pytest.raises(InputError, match="line 4: joint values outside the limits"):
        localize_files(obs, far, robot="kuka_kr60_3")


def test_cli_writes_base_pose(tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = CliRunner().invoke(
        app,
        [
            "localize",
            "total-station",
            str(TS_DATA / "obs_gsi8.gsi"),
            "--robot-points",
            str(TS_DATA / "robot_points.csv"),
            "-o",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    pose = BasePose.from_dict(json.loads((out / "base_pose.json").read_text()))
    assert pose.method == "total_station"
    assert np.linalg.norm(pose_error(pose.T_world_base, T_TRUE)[:3]) < 1e-3


def test_cli_bad_file_is_one_message(tmp_path: Path) -> None:
    bad = tmp_path / "bad.gsi"
    bad.write_text("110001+0000000A 21.102+1234567 22.102+10000000 31..00+00001000\n")
    out = tmp_path / "out"
    result = CliRunner().invoke(
        app,
        [
            "localize",
            "total-station",
            str(bad),
            "--robot-points",
            str(TS_DATA / "robot_points.csv"),
            "-o",
            str(out),
        ],
    )
    assert result.exit_code == 2
    assert "bad.gsi: line 1" in result.output and "Traceback" not in result.output
    assert not out.exists()


def test_project_with_measured_observations(tmp_path: Path) -> None:
    from fabflow.localize.total_station import localize_station
    from fabflow.project import parse_project

    text = f"""
name: measured
allow_outside_paths: true
elements:
  - task_points:
      - id: a
        pose: {{xyz: [1, 0, 0]}}
localization:
  method: total_station
  total_station:
    T_world_instrument: {{xyz: [0, 0, 0]}}
    observations: {TS_DATA / "obs_gsi8.gsi"}
    robot_points: {TS_DATA / "robot_points.csv"}
"""
    p = parse_project(text, base_dir=tmp_path)
    bp = localize_station(p, np.eye(4), np.random.default_rng(0), "S1")
    assert bp.station == "S1" and bp.quality["observations"].endswith("obs_gsi8.gsi")
    assert np.linalg.norm(pose_error(bp.T_world_base, T_TRUE)[:3]) < 1e-3
    bad = text.replace(f"    robot_points: {TS_DATA / 'robot_points.csv'}\n", "")
    with pytest.raises(InputError, match="must be given together"):
        parse_project(bad, base_dir=tmp_path)
