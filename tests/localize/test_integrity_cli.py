"""What ``fabflow localize`` does with a faulty reading, swapped prisms, a mis-surveyed anchor.

The data are the worked examples of docs/integrity.md (tests/data/integrity).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import DATA

FAULTS = DATA / "integrity"
ROBOT_POINTS = DATA / "total_station" / "robot_points.csv"
RANGES = DATA / "uwb" / "static" / "ranges.csv"
TRUE_BASE = np.array([6.0, 4.0, 0.5])  # tests/data/total_station/README.md


def _pose(out: Path) -> dict:
    return json.loads((out / "base_pose.json").read_text())


def test_bad_prism_reading_is_left_out(tmp_path: Path, cli) -> None:
    res = cli(
        "localize", "total-station", str(FAULTS / "obs_bad_reading.csv"),
        "--robot-points", str(ROBOT_POINTS), "-o", str(tmp_path / "o"),
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "excluded: left out prism P2" in res.stdout
    pose = _pose(tmp_path / "o")
    assert pose["integrity"]["status"] == "excluded"
    assert [e["observation"] for e in pose["integrity"]["excluded"]] == ["prism P2"]
    assert np.allclose(np.asarray(pose["T_world_base"])[:3, 3], TRUE_BASE, atol=1e-3)


def test_swapped_prisms_are_reassigned(tmp_path: Path, cli) -> None:
    res = cli(
        "localize", "total-station", str(FAULTS / "obs_swapped.csv"),
        "--robot-points", str(ROBOT_POINTS), "-o", str(tmp_path / "o"),
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "prism P3 <- reading of prism P2" in res.stdout
    assert res.stdout.count("readings reassigned") == 1
    pose = _pose(tmp_path / "o")
    assert pose["integrity"]["status"] == "ok"
    assert np.allclose(np.asarray(pose["T_world_base"])[:3, 3], TRUE_BASE, atol=1e-3)


def test_anchor_exclusion_beyond_the_alert_limit_fails(tmp_path: Path, cli) -> None:
    out = tmp_path / "o"
    res = cli(
        "localize", "uwb", str(RANGES), "--anchors", str(FAULTS / "anchors_a3_moved.yaml"),
        "-o", str(out),
    )  # fmt: skip
    assert res.returncode == 2
    assert "left out anchor A3" in res.stderr
    assert "exceeds the alert limit 10 mm" in res.stderr
    assert _pose(out)["integrity"]["status"] == "failed"  # written, with its tests


def test_a_wider_alert_limit_accepts_the_exclusion(tmp_path: Path, cli) -> None:
    clean, faulty = tmp_path / "clean", tmp_path / "faulty"
    anchors = DATA / "uwb" / "static" / "anchors.yaml"
    res = cli("localize", "uwb", str(RANGES), "--anchors", str(anchors), "-o", str(clean))
    assert res.returncode == 0, res.stderr
    assert "degraded" in res.stdout  # 4 anchors cannot protect 1 cm
    res = cli(
        "localize", "uwb", str(RANGES), "--anchors", str(FAULTS / "anchors_a3_moved.yaml"),
        "-o", str(faulty), "--alert-limit", "1.5",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    pose = _pose(faulty)
    assert pose["integrity"]["status"] == "excluded"
    d = np.asarray(pose["T_world_base"])[:3, 3] - np.asarray(_pose(clean)["T_world_base"])[:3, 3]
    sigma = np.sqrt(np.diag(np.asarray(pose["covariance"]))[:3])
    assert np.all(np.abs(d) < 3 * sigma)  # the moved anchor no longer pulls the pose


@pytest.mark.parametrize("value", ["-1", "0", "nan", "inf"])
def test_alert_limit_must_be_a_positive_length(tmp_path: Path, cli, value: str) -> None:
    res = cli(
        "localize", "uwb", str(RANGES), "--anchors", str(DATA / "uwb" / "static" / "anchors.yaml"),
        "-o", str(tmp_path / "o"), "--alert-limit", value,
    )  # fmt: skip
    assert res.returncode == 2
    assert "--alert-limit" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "o").exists()
