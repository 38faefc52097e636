"""A study on a real Dask cluster: scheduler file, data shipped to workers, versions checked.

The cluster is a ``dask scheduler`` and two ``dask worker`` processes on
127.0.0.1, started here through the scheduler file. The workers run in a
folder of their own and are refused every file of the project (an audit hook
loaded into them), so a study only gives the in-process result if it ships the
data its localization reads (an ICP map file, measured total station readings)
instead of their paths.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
from distributed import Client, LocalCluster
from helpers import DATA, TS_DATA
from typer.testing import CliRunner, Result

import fabflow.localize.icp as icp
import fabflow.sim.monte_carlo as mc
from fabflow.cli import app
from fabflow.errors import InputError, UnsupportedError
from fabflow.localize.methods import run_inputs
from fabflow.positioning.pointcloud_io import write_point_cloud
from fabflow.project import Project, load_project
from fabflow.sensors.site_map import simulated_site_map
from fabflow.sim.cluster import (
    check_environments,
    dask_client,
    environment,
    run_checked,
    scheduler_file_address,
)
from fabflow.sim.run import prepare_study

SMALL = DATA / "sim" / "project.yaml"
RUNS = 4
START_TIMEOUT = 60.0
"""Seconds the scheduler and the workers get to start on a busy machine."""

GUARD = '''\
"""Refuse this Dask worker every file under FABFLOW_TEST_FORBIDDEN (a project's folder)."""
import os
import sys

FORBIDDEN = os.path.abspath(os.environ["FABFLOW_TEST_FORBIDDEN"])


def guard(event, args):
    if event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
        path = os.path.abspath(os.fsdecode(args[0]))
        if path == FORBIDDEN or path.startswith(FORBIDDEN + os.sep):
            raise PermissionError(f"a worker may not read the project's files: {path}")


sys.addaudithook(guard)
'''


def small_with(localization: str) -> str:
    """The small test project's text with another ``localization`` section."""
    text = SMALL.read_text(encoding="utf-8")
    head, rest = text.split("localization:", 1)
    return head + localization + "elements:" + rest.split("elements:", 1)[1]


def write_icp_project(folder: Path) -> Path:
    """The small test project localized by ICP in a map file (the simulated site, PLY)."""
    folder.mkdir(parents=True, exist_ok=True)
    site = simulated_site_map((), 0.03)
    write_point_cloud(folder / "site_map.ply", site.points, site.normals)
    path = folder / "project.yaml"
    path.write_text(
        small_with("localization:\n  method: icp\n  icp:\n    map: site_map.ply\n"),
        encoding="utf-8",
    )
    return path


def write_measured_ts_project(folder: Path) -> Path:
    """The small test project localized from measured total station readings (files)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("obs_gsi8.gsi", "robot_points.csv"):
        shutil.copy(TS_DATA / name, folder / name)
    path = folder / "project.yaml"
    path.write_text(
        small_with(
            "localization:\n  method: total_station\n  total_station:\n"
            "    T_world_instrument: {xyz: [0, 0, 0]}\n"
            "    observations: obs_gsi8.gsi\n    robot_points: robot_points.csv\n"
        ),
        encoding="utf-8",
    )
    return path


def invoke(*args: str) -> Result:
    return CliRunner().invoke(app, ["simulate", *args], env={"COLUMNS": "200", "NO_COLOR": "1"})


def assert_same(a: mc.StudyResult, b: mc.StudyResult) -> None:
    """Bit for bit the same runs."""
    assert not a.failures and not b.failures, (a.failures, b.failures)
    for name in (
        "runs",
        "translation_m",
        "rotation_rad",
        "deviation_xyz",
        "localization_error",
        "localization_covariance",
        "integrity",
        "T_world_element_asbuilt_run0",
    ):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert [p.T_world_base.tobytes() for p in a.base_poses] == [
        p.T_world_base.tobytes() for p in b.base_poses
    ]


# ----------------------------------------------------------------- the real cluster


@dataclass(frozen=True)
class RealCluster:
    scheduler_file: Path
    project: Path
    """The ICP project, in a folder the workers may not read."""


def stop(procs: list[subprocess.Popen]) -> None:
    """Stop the processes this test started, newest first, one after the other (the
    workers while their scheduler still answers: under a second each)."""
    for proc in reversed(procs):
        if proc.poll() is None:
            proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=15)


@pytest.fixture(scope="module")
def real_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RealCluster]:
    root = tmp_path_factory.mktemp("cluster")
    project = write_icp_project(root / "project")
    workdir = root / "worker"  # holds no project file
    workdir.mkdir()
    (workdir / "guard.py").write_text(GUARD, encoding="utf-8")
    scheduler_file = root / "scheduler.json"
    env = dict(os.environ, FABFLOW_TEST_FORBIDDEN=str(project.parent))
    logs = [(root / f"{name}.log").open("w") for name in ("scheduler", "worker-1", "worker-2")]
    procs: list[subprocess.Popen] = []
    try:
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                 "--port", "0", "--no-dashboard", "--dashboard-address", "127.0.0.1:0",
                 "--scheduler-file", str(scheduler_file)],
                cwd=root, env=env, stdout=logs[0], stderr=subprocess.STDOUT,
            )
        )  # fmt: skip
        deadline = time.monotonic() + START_TIMEOUT
        while not scheduler_file.exists():
            assert procs[0].poll() is None, (root / "scheduler.log").read_text()
            assert time.monotonic() < deadline, "the scheduler did not start"
            time.sleep(0.1)
        for log in logs[1:]:
            procs.append(
                subprocess.Popen(
                    [sys.executable, "-m", "distributed.cli.dask_worker",
                     "--scheduler-file", str(scheduler_file), "--nthreads", "1",
                     "--no-nanny", "--host", "127.0.0.1", "--no-dashboard",
                     "--dashboard-address", "127.0.0.1:0", "--memory-limit", "0",
                     "--preload", str(workdir / "guard.py")],
                    cwd=workdir, env=env, stdout=log, stderr=subprocess.STDOUT,
                )
            )  # fmt: skip
        with Client(scheduler_file=str(scheduler_file), timeout=START_TIMEOUT) as client:
            client.wait_for_workers(2, timeout=START_TIMEOUT)
        yield RealCluster(scheduler_file, project)
    finally:
        stop(procs)
        for log in logs:
            log.close()


def test_a_study_through_a_scheduler_file_equals_in_process_bit_for_bit(
    real_cluster: RealCluster, tmp_path: Path
) -> None:
    """The done-when check: the workers cannot read the ICP map, yet give the same runs."""
    map_file = real_cluster.project.parent / "site_map.ply"
    study = prepare_study(load_project(real_cluster.project))
    assert set(study.file_data) == {"scan_map"}
    serial = mc.run_study(study, RUNS, seed=5)
    with dask_client(scheduler_file=real_cluster.scheduler_file, timeout=30) as client:
        workers = client.run(environment, on_error="return")
        assert len(workers) == 2
        check_environments(workers, environment())  # the real workers pass
        with pytest.raises(PermissionError, match="may not read the project's files"):
            client.submit(map_file.read_bytes, pure=False).result()  # the guard holds
        distributed = mc.run_study(study, RUNS, seed=5, client=client, chunk_size=1)
    assert_same(serial, distributed)

    # the command line: every file the same, bar the wall-clock times
    here, there = tmp_path / "here", tmp_path / "there"
    common = (str(real_cluster.project), "-n", str(RUNS), "--seed", "5", "--no-plots")
    result = invoke(*common, "-o", str(here), "--workers", "0")
    assert result.exit_code == 0, result.output
    result = invoke(*common, "-o", str(there), "--scheduler-file", str(real_cluster.scheduler_file))
    assert result.exit_code == 0, result.output
    assert f"{RUNS}/0" in result.output
    files = sorted(p.relative_to(here) for p in here.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(there) for p in there.rglob("*") if p.is_file())
    assert len(list((here / "localization").iterdir())) == study.n_visits
    for name in files:
        a, b = here / name, there / name
        if name.name == "summary.json":
            sa, sb = json.loads(a.read_text()), json.loads(b.read_text())
            del sa["runs"]["elapsed_s"], sb["runs"]["elapsed_s"]
            assert sa == sb
        elif name.name == "comparison.csv":
            rows = [list(csv.DictReader(f.open())) for f in (a, b)]
            for r in rows[0] + rows[1]:
                del r["seconds_per_run"]
            assert rows[0] == rows[1]
        else:
            assert a.read_bytes() == b.read_bytes(), name


def test_a_real_worker_that_cannot_import_the_check_is_named(
    real_cluster: RealCluster, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """As a worker without fabflow: the check's module exists on the client only."""
    (tmp_path / "client_only.py").write_text(
        "def environment():\n    return {}\n", encoding="utf-8"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    client_only = __import__("client_only")
    with Client(scheduler_file=str(real_cluster.scheduler_file), timeout=30) as client:
        answers = client.run(client_only.environment, on_error="return")
    assert len(answers) == 2
    with pytest.raises(UnsupportedError, match=r"tcp://127\.0\.0\.1:\d+ cannot run fabflow"):
        check_environments(answers, environment())


# ------------------------------------------------------------- data, not paths


@pytest.fixture(scope="module")
def icp_project(tmp_path_factory: pytest.TempPathFactory) -> Project:
    return load_project(write_icp_project(tmp_path_factory.mktemp("icp")))


@pytest.mark.parametrize("kind", ["icp", "total_station"])
def test_a_study_carries_the_data_of_its_files_and_gives_what_reading_them_gives(
    kind: str, icp_project: Project, tmp_path: Path
) -> None:
    """In process, the shipped data give bit for bit what reading the files by path gives."""
    project = icp_project if kind == "icp" else load_project(write_measured_ts_project(tmp_path))
    study = prepare_study(project)
    assert set(study.file_data) == {"icp": {"scan_map"}, "total_station": {"measured"}}[kind]
    # a map file is the one site map: no run draws its own
    assert run_inputs(project, kind, np.random.default_rng(0)) == {}
    icp._cached_file_map.cache_clear()
    by_path = mc.run_study(replace(study, file_data={}), 3, seed=2)
    assert_same(mc.run_study(study, 3, seed=2), by_path)


def test_a_study_of_a_project_without_files_carries_no_data() -> None:
    assert prepare_study(load_project(SMALL)).file_data == {}
    assert prepare_study(load_project(SMALL), "icp").file_data == {}  # a simulated map


# ---------------------------------------------------------------------- versions


def test_workers_with_other_versions_are_refused_naming_them() -> None:
    here = {"fabflow": "0.1.0", "python": "3.11.7", "numpy": "2.4.6", "scipy": "1.16.0"}
    check_environments({"tcp://10.0.0.5:4000": dict(here)}, here)
    with pytest.raises(UnsupportedError) as info:
        check_environments(
            {
                "tcp://10.0.0.5:4000": dict(here),
                "tcp://10.0.0.6:4000": {**here, "fabflow": "0.2.0"},
                "tcp://10.0.0.7:4000": {**here, "numpy": "1.26.4", "python": "3.12.1"},
            },
            here,
            "--scheduler-file",
        )
    message = str(info.value)
    assert message.startswith("--scheduler-file: ")
    assert "tcp://10.0.0.6:4000 runs fabflow 0.2.0 (here 0.1.0)" in message
    assert "tcp://10.0.0.7:4000 runs python 3.12.1 (here 3.11.7), numpy 1.26.4 (here 2.4.6)" in (
        message
    )
    assert "10.0.0.5" not in message


def test_a_worker_without_fabflow_or_with_many_differences_is_named() -> None:
    here = environment()
    with pytest.raises(UnsupportedError, match=r"tcp://w:1 cannot run fabflow \(Module"):
        check_environments({"tcp://w:1": ModuleNotFoundError("No module named 'fabflow'")}, here)
    old = {f"tcp://w:{i}": {**here, "fabflow": "0.0.1"} for i in range(8)}
    with pytest.raises(UnsupportedError, match=r"and 3 more worker\(s\)"):
        check_environments(old, here)


def test_a_task_on_a_worker_with_other_versions_fails_the_study(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A worker that joins after the check is refused by the task itself."""
    with (
        LocalCluster(
            n_workers=1,
            threads_per_worker=1,
            processes=False,
            protocol="tcp",
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        ) as cluster,
        Client(cluster) as client,
    ):
        assert client.submit(run_checked, environment(), sum, [1, 2]).result() == 3
        other = {**environment(), "fabflow": "0.0.1"}
        with pytest.raises(UnsupportedError, match=r"runs fabflow \S+ \(client 0\.0\.1\)"):
            client.submit(run_checked, other, sum, [1, 2]).result()
        monkeypatch.setattr(mc, "environment", lambda: other)
        with pytest.raises(UnsupportedError, match="same versions on every worker"):
            mc.run_study(prepare_study(load_project(SMALL)), 2, seed=0, client=client)


# --------------------------------------------------------- bad --scheduler-file


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "Dask scheduler file does not exist"),
        ("", "not a Dask scheduler file: not JSON"),
        ("{address: tcp://127.0.0.1:1", "line 1: not a Dask scheduler file: not JSON"),
        ('{"type": "Scheduler", "workers": {}}', "no scheduler 'address' in it"),
        ('["tcp://127.0.0.1:1"]', "no scheduler 'address' in it"),
        ('{"address": "tls://127.0.0.1:1"}', "address: unsupported Dask scheduler address"),
        ('{"address": "tcp://127.0.0.1:1"}', "cannot connect to the Dask scheduler at"),
    ],
)
def test_a_bad_scheduler_file_is_one_message_and_exit_2(
    tmp_path: Path, content: str | None, message: str
) -> None:
    path = tmp_path / "scheduler.json"
    if content is not None:
        path.write_text(content, encoding="utf-8")
    out = tmp_path / "never"
    result = invoke(
        str(SMALL), "-o", str(out), "-n", "2", "--scheduler-file", str(path), "--timeout", "0.5"
    )
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert "Traceback" not in result.output
    assert not out.exists()


def test_scheduler_and_scheduler_file_exclude_each_other(tmp_path: Path) -> None:
    path = tmp_path / "scheduler.json"
    path.write_text('{"address": "tcp://127.0.0.1:1"}', encoding="utf-8")
    result = invoke(
        str(SMALL), "-o", str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:1",
        "--scheduler-file", str(path),
    )  # fmt: skip
    assert result.exit_code == 2, result.output
    assert "--scheduler-file: give either --scheduler or --scheduler-file" in result.output


def test_a_scheduler_file_gives_its_address(tmp_path: Path) -> None:
    path = tmp_path / "scheduler.json"
    path.write_text(
        json.dumps({"type": "Scheduler", "address": "tcp://127.0.0.1:8786", "workers": {}}),
        encoding="utf-8",
    )
    assert scheduler_file_address(path) == "tcp://127.0.0.1:8786"
    with pytest.raises(InputError, match="is a folder"):
        scheduler_file_address(tmp_path)


def test_a_scheduler_file_without_workers_waits_for_the_timeout(tmp_path: Path) -> None:
    with LocalCluster(
        n_workers=0,
        processes=False,
        protocol="tcp",
        dashboard_address=None,
        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
    ) as cluster:
        path = tmp_path / "scheduler.json"
        path.write_text(json.dumps({"address": cluster.scheduler_address}), encoding="utf-8")
        with pytest.raises(InputError, match=r"has no worker after 0.5 s.*--scheduler-file"):
            with dask_client(scheduler_file=path, timeout=0.5):
                pass
