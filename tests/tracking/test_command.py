"""``fabflow track`` end to end on the example project, shortened to one layer."""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import pytest
import yaml
from helpers import PROJECTS, run_cli

from fabflow.errors import InputError
from fabflow.project import load_project
from fabflow.tracking.report import CSV_COLUMNS
from fabflow.tracking.run import track_print


def _short_project(tmp_path: Path, **tracking: float) -> Path:
    """The example with one layer and a 2 s settle (a 45 s print)."""
    folder = tmp_path / "excavator_print"
    shutil.copytree(PROJECTS / "excavator_print", folder)
    data = yaml.safe_load((folder / "project.yaml").read_text())
    data["elements"][0]["print_path"]["n_layers"] = 1
    data["tracking"] = {"settle_s": 2.0, **tracking}
    (folder / "project.yaml").write_text(yaml.safe_dump(data))
    return folder


@pytest.fixture(scope="module")
def tracked(tmp_path_factory) -> tuple[Path, dict]:
    tmp = tmp_path_factory.mktemp("track")
    out = tmp / "out"
    result = run_cli("track", str(_short_project(tmp)), "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stdout + result.stderr
    return out, json.loads((out / "summary.json").read_text())


def test_track_writes_the_csv_the_plot_and_the_summary(tracked) -> None:
    out, summary = tracked
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "summary.json",
        "tracking.csv",
        "tracking.png",
    ]
    with (out / "tracking.csv").open() as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == CSV_COLUMNS
    assert len(rows) - 1 == summary["samples"]
    values = [float(v) for row in rows[1:] for v in row]
    assert all(math.isfinite(v) for v in values)
    t = [float(r[0]) for r in rows[1:]]
    assert t == sorted(t) and abs(t[1] - t[0] - 0.01) < 1e-9  # 100 Hz
    assert (out / "tracking.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_closed_loop_beats_open_loop_and_the_fused_estimate_beats_each_sensor(tracked) -> None:
    _, s = tracked
    closed, open_ = s["tracking"]["closed_loop"], s["tracking"]["open_loop"]
    assert closed["rmse_m"] < 0.5 * open_["rmse_m"]
    assert s["tracking"]["improvement"] == pytest.approx(open_["rmse_m"] / closed["rmse_m"])
    est = s["estimation"]
    assert est["fused"]["rmse_m"] < est["kinematics"]["rmse_m"]
    assert est["fused"]["rmse_m"] < est["icp"]["rmse_m"]
    assert s["icp"]["applied"] > 0.9 * s["icp"]["fixes"]
    assert s["speed"]["simulated_s"] == pytest.approx(s["speed"]["print_s"] + 2.0, abs=0.02)


@pytest.mark.parametrize(
    ("project", "message"),
    [("cabin", "hydraulic excavator"), ("stone_wall", "a stone wall is built from found stones")],
)
def test_track_refuses_what_it_cannot_print(tmp_path, project, message) -> None:
    result = run_cli("track", str(PROJECTS / project), "-o", str(tmp_path / "out"))
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stdout + result.stderr
    assert not (tmp_path / "out").exists()


def test_track_refuses_an_excavator_project_without_print_paths(tmp_path) -> None:
    folder = _short_project(tmp_path)
    data = yaml.safe_load((folder / "project.yaml").read_text())
    data["elements"] = [{"task_points": [{"id": "T1", "pose": {"xyz": [4.5, -0.8, 0.0]}}]}]
    (folder / "project.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InputError, match="follows print paths"):
        track_print(load_project(folder), "open")


def test_a_print_longer_than_the_bound_is_refused_before_it_runs(tmp_path) -> None:
    project = load_project(_short_project(tmp_path, max_duration_s=10.0))
    with pytest.raises(InputError, match="max_duration_s"):
        track_print(project, "open")


def test_a_perfect_machine_tracks_open_loop_to_its_dynamics_only(tmp_path) -> None:
    folder = _short_project(tmp_path)
    data = yaml.safe_load((folder / "project.yaml").read_text())
    data["simulation"] = {"sensor_noise": False}
    (folder / "project.yaml").write_text(yaml.safe_dump(data))
    run = track_print(load_project(folder), "open")
    err = ((run.p_true - run.p_ref) ** 2).sum(axis=1) ** 0.5
    # no sensor or geometry error: what is left is the hydraulics' lag at the bends
    # and the turn encoder's 0.92 deg steps (the KF smooths them to a few mm)
    assert err.max() < 0.02
    assert (err**2).mean() ** 0.5 < 0.006
