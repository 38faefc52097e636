"""Monte Carlo studies: Dask equals serial, a real LocalCluster, failures, output files."""

from __future__ import annotations

import csv
import json
import math
import os
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import dask
import numpy as np
import psutil
import pytest
from distributed import Client, LocalCluster
from helpers import DATA

import fabflow.sim.monte_carlo as mc
from fabflow.errors import InputError, LocalizationError
from fabflow.preview.inputs import read_base_poses, read_deviations
from fabflow.project import load_project
from fabflow.sim.monte_carlo import dask_client, run_study, scheduler_address, summarize
from fabflow.sim.report import parse_methods, simulate_project, write_study
from fabflow.sim.run import Study, prepare_study
from fabflow.transforms.se3 import perturb

SMALL = DATA / "sim" / "project.yaml"
LOCAL_HTTP = {"dashboard_address": "127.0.0.1:0"}
"""No dashboard; the scheduler's HTTP server (health, metrics) on localhost, a free port."""


@pytest.fixture(scope="module")
def study() -> Study:
    return prepare_study(load_project(SMALL))


@pytest.fixture(scope="module")
def cluster() -> Iterator[LocalCluster]:
    """A real dask.distributed cluster on TCP (in-process worker, to stay fast)."""
    with LocalCluster(
        n_workers=1,
        threads_per_worker=2,
        processes=False,
        protocol="tcp",
        dashboard_address=None,
        scheduler_kwargs=LOCAL_HTTP,
    ) as c:
        yield c


def assert_same(a: mc.StudyResult, b: mc.StudyResult) -> None:
    np.testing.assert_array_equal(a.runs, b.runs)
    np.testing.assert_array_equal(a.deviation_xyz, b.deviation_xyz)
    np.testing.assert_array_equal(a.translation_m, b.translation_m)
    np.testing.assert_array_equal(a.localization_error, b.localization_error)
    np.testing.assert_array_equal(a.localization_covariance, b.localization_covariance)


def test_dask_through_the_scheduler_address_equals_serial(
    study: Study, cluster: LocalCluster
) -> None:
    serial = run_study(study, 7, seed=42, chunk_size=7)
    assert cluster.scheduler_address.startswith("tcp://")
    done: list[int] = []
    with dask_client(cluster.scheduler_address) as client:
        distributed = run_study(
            study, 7, seed=42, client=client, chunk_size=2, progress=done.append
        )
    assert sorted(done) == [1, 2, 2, 2]
    assert_same(serial, distributed)
    assert distributed.base_poses[0].station == study.stations[0].id


def test_chunking_does_not_change_results(study: Study) -> None:
    assert_same(
        run_study(study, 5, seed=3, chunk_size=1), run_study(study, 5, seed=3, chunk_size=5)
    )


def test_a_failed_run_is_reported_with_its_seed(
    study: Study, monkeypatch: pytest.MonkeyPatch, cluster: LocalCluster
) -> None:
    real = mc.simulate_run

    def flaky(st: Study, run: int, seed: int, keep_poses: bool = False) -> mc.RunResult:
        if run == 2:
            raise LocalizationError("ICP fitness 0.1 is below the required 0.5")
        return real(st, run, seed, keep_poses)

    monkeypatch.setattr(mc, "simulate_run", flaky)
    result = run_study(study, 4, seed=9)
    assert result.runs.tolist() == [0, 1, 3]
    assert len(result.failures) == 1
    failure = result.failures[0]
    assert (failure.run, failure.seed) == (2, 9)
    assert "LocalizationError: ICP fitness" in failure.error
    summary = summarize(study, result)
    assert summary["runs"] == {
        "requested": 4,
        "completed": 3,
        "failed": 1,
        "elapsed_s": result.elapsed_s,
    }
    assert summary["failures"] == [{"run": 2, "seed": 9, "error": failure.error}]


def test_summary_figures(study: Study) -> None:
    result = run_study(study, 6, seed=1)
    s = summarize(study, result)
    t = result.translation_m
    assert s["translation_m"]["rmse"] == pytest.approx(np.sqrt(np.mean(t**2)))
    assert s["translation_m"]["max"] == pytest.approx(t.max())
    assert s["translation_m"]["p95"] == pytest.approx(np.percentile(t, 95))
    tol = study.project.tolerances
    within = (t <= tol.position) & (result.rotation_rad <= math.radians(tol.rotation_deg))
    assert s["within_tolerance"] == pytest.approx(within.mean())
    assert list(s["per_station"]) == list(dict.fromkeys(st.id for st in study.stations))
    loc = s["localization"]
    assert set(loc["sigma_ratio"]) == {"x", "y", "z", "rz"}  # roll, pitch: not observed
    assert all(0.2 < r < 5 for r in loc["sigma_ratio"].values())
    json.dumps(s)


def test_sigma_ratio_of_an_honest_and_an_overconfident_covariance() -> None:
    rng = np.random.default_rng(0)
    sigma = np.array([0.01, 0.02, 0.03, 2.0, 2.0, 0.004])
    errors = rng.normal(size=(20000, 6)) * sigma
    cov = np.broadcast_to(np.diag(sigma**2), (20000, 6, 6))
    honest = mc.sigma_ratio(errors, cov)
    assert set(honest) == {"x", "y", "z", "rz"}
    assert all(abs(v - 1) < 0.03 for v in honest.values())
    assert mc.sigma_ratio(2 * errors, cov)["x"] == pytest.approx(2 * honest["x"])


def test_output_folder_is_what_the_preview_reads(study: Study, tmp_path: Path) -> None:
    result = run_study(study, 5, seed=2)
    write_study(tmp_path, study, result)
    for name in (
        "elements.csv",
        "runs.csv",
        "visits.csv",
        "summary.json",
        "deviation_histogram.png",
        "deviation_heat_map.png",
        "localization_error.png",
    ):
        assert (tmp_path / name).stat().st_size > 0, name
    deviations = read_deviations(tmp_path)
    assert set(deviations) == set(study.element_ids)
    np.testing.assert_allclose(
        [deviations[e] for e in study.element_ids], result.translation_m.mean(0), rtol=1e-5
    )
    with (tmp_path / "asbuilt_run0.csv").open() as f:
        asbuilt = list(csv.DictReader(f))
    assert [r["element"] for r in asbuilt] == list(study.element_ids)
    for i, r in enumerate(asbuilt):
        planned = np.array([float(r[f"planned_{c}_m"]) for c in "xyz"])
        built = np.array([float(r[f"asbuilt_{c}_m"]) for c in "xyz"])
        np.testing.assert_allclose(planned, study.T_world_element[i, :3, 3], atol=1e-6)
        # the file keeps 6 significant digits: up to 5e-6 m per coordinate below 10 m
        assert np.linalg.norm(built - planned) == pytest.approx(
            result.translation_m[0, i], abs=2e-5
        )
        assert float(r["run0_translation_m"]) == pytest.approx(result.translation_m[0, i], rel=5e-6)
    poses = read_base_poses(tmp_path)  # by work package index (visit_01 -> 0)
    assert set(poses) == set(range(study.n_visits))
    assert poses[0].station == study.stations[0].id
    with (tmp_path / "runs.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["run"]) for r in rows] == [0, 1, 2, 3, 4]
    with (tmp_path / "visits.csv").open() as f:
        visits = list(csv.DictReader(f))
    assert len(visits) == 5 * study.n_visits
    assert float(visits[0]["error_x_m"]) == pytest.approx(
        result.localization_error[0, 0, 0], abs=1e-6
    )


def test_method_comparison_shares_plan_and_seeds(tmp_path: Path) -> None:
    project = load_project(SMALL)
    rows = simulate_project(project, tmp_path, 3, 4, ["uwb", "total_station"], plots=False)
    assert [r["method"] for r in rows] == ["uwb", "total_station"]
    assert (tmp_path / "uwb" / "elements.csv").exists()
    assert (tmp_path / "total_station" / "elements.csv").exists()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert set(summary["methods"]) == {"uwb", "total_station"}
    with (tmp_path / "comparison.csv").open() as f:
        table = list(csv.DictReader(f))
    assert [r["method"] for r in table] == ["uwb", "total_station"]
    # same seeds, so the same parking error: estimate + error = the same true base pose
    true = []
    for m in ("uwb", "total_station"):
        [path] = (tmp_path / m / "localization").glob("visit_01_*.json")
        pose = json.loads(path.read_text())
        with (tmp_path / m / "visits.csv").open() as f:
            first = next(csv.DictReader(f))
        error = [float(first[k]) for k in first if k.startswith("error_")]
        true.append(perturb(np.array(pose["T_world_base"]), error))
    np.testing.assert_allclose(true[0], true[1], atol=1e-6)


def test_parse_methods() -> None:
    assert parse_methods(" uwb, icp,uwb ") == ["uwb", "icp"]
    with pytest.raises(Exception, match=r"unknown localization method.*gps"):
        parse_methods("uwb,gps")
    with pytest.raises(Exception, match="none given"):
        parse_methods(" , ")


def test_unreachable_scheduler_is_an_input_error(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> Client:
        raise OSError("Timed out trying to connect to tcp://127.0.0.1:1")

    monkeypatch.setattr("distributed.Client", refuse)
    with pytest.raises(Exception, match="cannot connect to the Dask scheduler") as info:
        with dask_client("tcp://127.0.0.1:1"):
            pass
    assert type(info.value).__name__ == "InputError"


def test_every_run_failing_still_writes_a_complete_report(
    study: Study, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    def fail(st: Study, run: int, seed: int, keep_poses: bool = False) -> mc.RunResult:
        raise LocalizationError("no clear localization point")

    monkeypatch.setattr(mc, "simulate_run", fail)
    result = run_study(study, 3, seed=1)
    summary = write_study(tmp_path, study, result)
    assert summary["runs"]["completed"] == 0
    assert [f["run"] for f in summary["failures"]] == [0, 1, 2]
    assert math.isnan(summary["translation_m"]["rmse"])
    with (tmp_path / "runs.csv").open() as f:
        assert [r["status"] for r in csv.DictReader(f)] == ["failed"] * 3
    assert (tmp_path / "localization_error.png").exists()


def test_a_method_that_cannot_be_calibrated_fails_all_its_runs(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import fabflow.sim.report as report

    def refuse(study: Study, n: int) -> np.ndarray:
        if study.method == "total_station":
            raise LocalizationError("no clear localization point")
        return real(study, n)

    real = report.calibrate_covariance
    monkeypatch.setattr(report, "calibrate_covariance", refuse)
    rows = simulate_project(
        load_project(SMALL),
        tmp_path,
        4,
        0,
        ["uwb", "total_station"],
        plots=False,
        fidelity="covariance",
    )
    by_method = {r["method"]: r for r in rows}
    assert by_method["uwb"]["runs_completed"] == 4
    assert by_method["total_station"]["runs_failed"] == 4
    summary = json.loads((tmp_path / "total_station" / "summary.json").read_text())
    assert summary["fidelity"] == "covariance"
    assert "covariance calibration failed" in summary["failures"][0]["error"]
    uwb = json.loads((tmp_path / "uwb" / "summary.json").read_text())
    assert uwb["fidelity"] == "covariance"


def listening() -> set[tuple[str, int]]:
    """The (address, port) pairs this process listens on."""
    proc = psutil.Process()
    get = getattr(proc, "net_connections", None) or proc.connections
    conns = get(kind="inet")
    return {(c.laddr.ip, c.laddr.port) for c in conns if c.status == psutil.CONN_LISTEN}


@pytest.mark.parametrize("dashboard", [False, True])
def test_the_local_cluster_listens_on_localhost_only(dashboard: bool) -> None:
    before = listening()
    with dask_client(None, n_workers=0, dashboard=dashboard) as client:
        new = listening() - before
        http = client.scheduler_info()["services"]["dashboard"]  # the HTTP server, always on
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{http}/status", timeout=10) as r:
                status = r.status
        except urllib.error.HTTPError as exc:
            status = exc.code
    assert new and {ip for ip, _ in new} == {"127.0.0.1"}
    assert status == (200 if dashboard else 404)


def test_a_scheduler_without_workers_is_a_clear_error() -> None:
    with LocalCluster(
        n_workers=0,
        processes=False,
        protocol="tcp",
        dashboard_address=None,
        scheduler_kwargs=LOCAL_HTTP,
    ) as cluster:
        t0 = time.perf_counter()
        with pytest.raises(InputError, match=r"has no worker after 0.5 s.*--timeout"):
            with dask_client(cluster.scheduler_address, timeout=0.5):
                pass
        assert time.perf_counter() - t0 < 10


def test_an_unreachable_scheduler_is_a_clear_error() -> None:
    with pytest.raises(InputError, match="cannot connect to the Dask scheduler"):
        with dask_client("tcp://127.0.0.1:1", timeout=0.5):
            pass


@pytest.mark.parametrize(
    "address", ["foo", "", "tcp://", "http://host:8786", "tls://127.0.0.1:1", "h:99999", "[::1"]
)
def test_a_malformed_scheduler_address_is_refused(address: str) -> None:
    with pytest.raises(InputError, match="scheduler address"):
        scheduler_address(address)


def test_scheduler_addresses() -> None:
    assert scheduler_address("127.0.0.1:8786") == "tcp://127.0.0.1:8786"
    assert scheduler_address(" tcp://[::1]:8786 ") == "tcp://[::1]:8786"


@pytest.mark.parametrize("timeout", [0.0, -1.0, math.nan, math.inf])
def test_a_bad_timeout_is_refused(timeout: float) -> None:
    with pytest.raises(InputError, match="--timeout"):
        with dask_client("tcp://127.0.0.1:1", timeout=timeout):
            pass


def _heap_environ() -> tuple[str | None, str | None]:
    return os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.environ.get("OPENBLAS_NUM_THREADS")


def test_the_local_cluster_workers_keep_glibcs_heap_default() -> None:
    # Dask's nanny returns freed heap at once (64 KiB); a simulated run's many small
    # arrays made that 1.4 times slower, so the local workers run without it and
    # keep the rest of Dask's environment (one linear-algebra thread each)
    assert "MALLOC_TRIM_THRESHOLD_" in dask.config.get("distributed.nanny.pre-spawn-environ")
    with dask_client(None, n_workers=1) as client:
        [(trim, threads)] = client.run(_heap_environ).values()
    assert trim is None and threads == "1"
    assert "MALLOC_TRIM_THRESHOLD_" in dask.config.get("distributed.nanny.pre-spawn-environ")
