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


# ------------------------------------------------ UWB: links, names, what is written

ANCHORS = DATA / "uwb" / "static" / "anchors.yaml"


def _truth_static() -> np.ndarray:
    # tests/data/uwb/generate.py: platform at (1.6, 2.2), heading 30 deg; base at (0.3, 0, 0.6)
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    return np.array([1.6 + 0.3 * c, 2.2 + 0.3 * s, 0.6])


def _link_fault(path: Path, offset: float, tag: str = "1", anchor: str = "A3") -> Path:
    """The sample ranges with every range of one tag-anchor link ``offset`` metres long."""
    lines = RANGES.read_text().splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        t, k, a, r = line.split(",")
        out.append(f"{t},{k},{a},{float(r) + offset:.4f}" if (k, a) == (tag, anchor) else line)
    path.write_text("\n".join(out) + "\n")
    return path


def test_a_link_a_metre_long_is_not_trimmed_silently(tmp_path: Path, cli) -> None:
    ranges = _link_fault(tmp_path / "ranges.csv", 1.0)
    res = cli("localize", "uwb", str(ranges), "--anchors", str(ANCHORS), "-o", str(tmp_path / "o"))
    integrity = _pose(tmp_path / "o")["integrity"]
    assert integrity["status"] != "ok"
    # its ranges are on the record: left out with the anchor, and the guard applies
    assert [e["observation"] for e in integrity["excluded"]] == ["anchor A3"]
    assert integrity["excluded"][0]["ranges"] >= 118
    assert res.returncode == 2 and "exceeds the alert limit" in res.stderr


def test_a_link_fault_never_gives_a_wrong_pose_that_passes(tmp_path: Path, cli) -> None:
    ranges = _link_fault(tmp_path / "ranges.csv", 0.4)
    out = tmp_path / "o"
    res = cli(
        "localize", "uwb", str(ranges), "--anchors", str(ANCHORS), "-o", str(out),
        "--alert-limit", "0.5",
    )  # fmt: skip
    pose = _pose(out)
    if pose["integrity"]["status"] == "failed":
        assert res.returncode == 2
    else:
        d = np.asarray(pose["T_world_base"])[:3, 3] - _truth_static()
        sigma = np.sqrt(np.diag(np.asarray(pose["covariance"]))[:3])
        assert np.all(np.abs(d) < 3 * sigma)
    assert "anchor A4 from tag 0" not in str(pose["integrity"]["excluded"])


def test_anchor_names_with_a_space_work_through_the_command(tmp_path: Path, cli) -> None:
    anchors = tmp_path / "anchors.yaml"
    anchors.write_text(ANCHORS.read_text().replace("  A3:", "  A 3:"))
    ranges = _link_fault(tmp_path / "ranges.csv", 0.4)
    ranges.write_text(ranges.read_text().replace(",A3,", ",A 3,"))
    out = tmp_path / "o"
    res = cli(
        "localize", "uwb", str(ranges), "--anchors", str(anchors), "-o", str(out),
        "--alert-limit", "1.5",
    )  # fmt: skip
    assert "Traceback" not in res.stderr, res.stderr
    assert res.returncode == 0, res.stderr
    assert "left out anchor A 3" in res.stdout
    assert [e["observation"] for e in _pose(out)["integrity"]["excluded"]] == ["anchor A 3"]


def test_single_nlos_ranges_are_rejected_on_the_record(tmp_path: Path, cli) -> None:
    lines = RANGES.read_text().splitlines()
    t, k, a, r = lines[5].split(",")  # one range of tag 0 to A1, 1 m long (NLOS)
    lines[5] = f"{t},{k},{a},{float(r) + 1.0:.4f}"
    ranges = tmp_path / "ranges.csv"
    ranges.write_text("\n".join(lines) + "\n")
    res = cli("localize", "uwb", str(ranges), "--anchors", str(ANCHORS), "-o", str(tmp_path / "o"))
    assert res.returncode == 0, res.stderr
    integrity = _pose(tmp_path / "o")["integrity"]
    assert integrity["status"] == "ok"
    rejected = integrity["checks"]["rejected_ranges"]
    assert rejected["per_link"].get(f"anchor {a} from tag {k}", 0) >= 1
