"""``fabflow simulate`` end to end on a small project."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from distributed import LocalCluster
from helpers import DATA
from typer.testing import CliRunner, Result

import fabflow.sim.monte_carlo as mc
from fabflow.cli import app
from fabflow.errors import LocalizationError

SMALL = DATA / "sim" / "project.yaml"
LOCAL_HTTP = {"dashboard_address": "127.0.0.1:0"}
"""No dashboard; the scheduler's HTTP server (health, metrics) on localhost, a free port."""


def invoke(*args: str) -> Result:
    return CliRunner().invoke(app, ["simulate", *args], env={"COLUMNS": "200", "NO_COLOR": "1"})


def test_simulate_in_process(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    result = invoke(str(SMALL), "-o", str(out), "--runs", "4", "--workers", "0", "--seed", "8")
    assert result.exit_code == 0, result.output
    assert "fabflow simulate: sim-small, 4 runs" in result.output
    assert "uwb" in result.output and "4/0" in result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"]["completed"] == 4 and summary["seed"] == 8
    assert summary["method"] == "uwb"
    with (out / "elements.csv").open() as f:
        assert sorted(r["element"] for r in csv.DictReader(f)) == ["P1", "P2", "P3", "P4"]
    for png in ("deviation_histogram.png", "deviation_heat_map.png", "localization_error.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"


def test_simulate_through_a_scheduler_compares_methods(tmp_path: Path) -> None:
    out = tmp_path / "cmp"
    with LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=False,
        protocol="tcp",
        dashboard_address=None,
        scheduler_kwargs=LOCAL_HTTP,
    ) as cluster:
        result = invoke(
            str(SMALL),
            "-o",
            str(out),
            "-n",
            "3",
            "--methods",
            "uwb,total_station",
            "--scheduler",
            cluster.scheduler_address,
            "--no-plots",
        )
    assert result.exit_code == 0, result.output
    assert "total_station" in result.output
    with (out / "comparison.csv").open() as f:
        assert [r["method"] for r in csv.DictReader(f)] == ["uwb", "total_station"]
    assert (out / "uwb" / "elements.csv").exists()
    assert not (out / "uwb" / "deviation_histogram.png").exists()


def test_bad_methods_is_one_message_and_exit_2(tmp_path: Path) -> None:
    out = tmp_path / "never"
    result = invoke(str(SMALL), "-o", str(out), "--methods", "uwb,gps", "--workers", "0")
    assert result.exit_code == 2
    assert "unknown localization method(s) gps" in result.output
    assert "Traceback" not in result.output
    assert not out.exists()


def test_missing_project_is_exit_2(tmp_path: Path) -> None:
    result = invoke(str(tmp_path / "nope.yaml"), "-o", str(tmp_path / "o"), "--workers", "0")
    assert result.exit_code == 2
    assert "project file does not exist" in result.output


def test_simulate_covariance_fidelity(tmp_path: Path) -> None:
    out = tmp_path / "fast"
    args = ["-n", "50", "--workers", "0", "--no-plots", "--fidelity", "covariance"]
    result = invoke(str(SMALL), "-o", str(out), *args)
    assert result.exit_code == 0, result.output
    assert "(covariance)" in result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["fidelity"] == "covariance" and summary["runs"]["completed"] == 50
    bad = invoke(str(SMALL), "-o", str(tmp_path / "x"), "--workers", "0", "--fidelity", "fast")
    assert bad.exit_code == 2 and "unknown fidelity" in bad.output


def test_a_scheduler_without_workers_exits_2_after_the_timeout(tmp_path: Path) -> None:
    out = tmp_path / "never"
    with LocalCluster(
        n_workers=0,
        processes=False,
        protocol="tcp",
        dashboard_address=None,
        scheduler_kwargs=LOCAL_HTTP,
    ) as c:
        result = invoke(
            str(SMALL), "-o", str(out), "-n", "2", "--scheduler", c.scheduler_address,
            "--timeout", "0.5",
        )  # fmt: skip
    assert result.exit_code == 2, result.output
    assert "has no worker after 0.5 s" in result.output
    assert not out.exists() and sorted(tmp_path.iterdir()) == []


def test_every_run_of_a_method_failing_exits_2_naming_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def fail(*args: object, **kwargs: object) -> None:
        raise LocalizationError("no clear localization point")

    monkeypatch.setattr(mc, "simulate_run", fail)
    out = tmp_path / "sim"
    result = invoke(str(SMALL), "-o", str(out), "-n", "2", "--workers", "0", "--no-plots")
    assert result.exit_code == 2, result.output
    assert "every run of method 'uwb' failed" in result.output
    assert "Traceback" not in result.output
    with (out / "runs.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["status"] for r in rows] == ["failed"] * 2
    assert "no clear localization point" in rows[0]["error"]


def test_simulate_compares_the_total_stations_procedures(tmp_path: Path) -> None:
    out = tmp_path / "ab"
    result = invoke(
        str(SMALL),
        "-o",
        str(out),
        "-n",
        "2",
        "--workers",
        "0",
        "--methods",
        "total_station",
        "--stationing",
        "control_points,robot_points",
    )
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["methods"]) == {
        "total_station-control_points",
        "total_station-robot_points",
    }
    for study in summary["methods"].values():
        setups = study["setups"]
        assert setups[0]["packages"][0] == 1
        assert all(0 < s["xy_error_m"]["mean"] <= s["xy_error_m"]["max"] for s in setups)
    assert "Procedure A" in result.output and "T1" in result.output
    assert (out / "total_station-robot_points" / "summary.json").exists()


def test_an_unknown_stationing_is_refused(tmp_path: Path) -> None:
    result = invoke(
        str(SMALL),
        "-o",
        str(tmp_path / "x"),
        "--workers",
        "0",
        "--methods",
        "total_station",
        "--stationing",
        "tripod",
    )
    assert result.exit_code == 2, result.output
    assert "unknown stationing 'tripod'" in result.output
