"""A killed ``fabflow build`` leaves the old output or the new one, and the next run cleans up.

``kill_harness.py`` stops builds of a small project at every named point of a
run (before each build stage, and at the points of :mod:`fabflow.output`) with
SIGKILL and SIGTERM, with and without the atomic exchange, and after seeded
random delays. Each case starts from an older complete output of a variant of
the project, so "old" and "new" can be told apart; the outputs are compared
with reference builds of both.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import DATA, ROOT

from fabflow.build.runner import run_build, stages
from fabflow.errors import InputError
from fabflow.output import MARKER, atomic_output_dir
from fabflow.project import load_project

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="the harness forks and reads /proc"
)

PROJECT = DATA / "sim" / "project.yaml"
HARNESS = Path(__file__).with_name("kill_harness.py")
UNSTABLE = {"plan.json", "site_plan.dxf", "summary.json"}
"""Files holding timings or time stamps: compared by name, not content."""
POINTS = [
    "staging-created",
    *(f"stage-{name}" for name, _ in stages()),
    "before-replace",
    "replaced",
]
NEW_FROM = {"moved-aside", "replaced"}
"""Points at which the new output is already in place."""


def snapshot(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def state(out: Path, refs: dict[str, dict[str, bytes]]) -> str:
    """``absent``, ``old`` or ``new`` (complete and equal to that reference), else fail."""
    if not out.exists():
        return "absent"
    files = snapshot(out)
    assert MARKER in files
    json.loads(files["summary.json"])
    name = json.loads(files["project.json"])["project"]["name"]
    which = {"sim-small": "new", "sim-small-old": "old"}[name]
    ref = refs[which]
    assert sorted(files) == sorted(ref), f"{out} is not a complete {which} output"
    for rel, data in ref.items():
        if rel not in UNSTABLE:
            assert files[rel] == data, f"{out}/{rel} differs from the {which} output"
    return which


@pytest.fixture(scope="module")
def refs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, bytes]]:
    folder = tmp_path_factory.mktemp("refs")
    old_project = folder / "old.yaml"
    old_project.write_text(PROJECT.read_text().replace("name: sim-small", "name: sim-small-old"))
    run_build(load_project(old_project), folder / "old")
    run_build(load_project(PROJECT), folder / "new")
    return {"old": snapshot(folder / "old"), "new": snapshot(folder / "new")}


def put_old(out: Path, refs: dict) -> None:
    for rel, data in refs["old"].items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(data)


def cases(tmp_path: Path, refs: dict) -> list[dict]:
    specs: list[dict] = []
    for point in POINTS:
        for sig in ("SIGKILL", "SIGTERM"):
            specs.append({"point": point, "signal": sig})
    for point in ("before-replace", "moved-aside", "replaced"):
        for sig in ("SIGKILL", "SIGTERM"):
            specs.append({"point": point, "signal": sig, "exchange": False})
    for point, sig in (("staging-created", "SIGKILL"), ("stage-program", "SIGTERM")):
        specs.append({"point": point, "signal": sig, "initial": "absent"})
    specs.append({"point": "replaced", "signal": "SIGKILL", "initial": "absent"})
    rng = random.Random(17)
    for k in range(8):
        specs.append({"delay": rng.uniform(0.0, 0.3), "signal": ("SIGKILL", "SIGTERM")[k % 2]})
    for k, spec in enumerate(specs):
        out = tmp_path / f"case{k:02d}" / "out"
        spec.update(out=str(out), log=str(tmp_path / f"case{k:02d}.log"))
        spec.setdefault("exchange", True)
        if spec.setdefault("initial", "old") == "old":
            put_old(out, refs)
        else:
            out.parent.mkdir(parents=True)
    return specs


def expected_after_kill(case: dict) -> set[str]:
    if case.get("delay") is not None:
        return {"old", "new"}
    if case["point"] in NEW_FROM:
        if case["point"] == "moved-aside" and case["signal"] == "SIGKILL":
            return {"absent"}  # no exchange: the previous output waits beside OUT
        return {"new"}
    return {case["initial"]}


def next_run_that_fails(out: Path) -> None:
    with pytest.raises(InputError, match="stop here"), atomic_output_dir(out):
        raise InputError("stop here")


def test_a_kill_at_any_point_leaves_the_old_or_the_new_output(
    tmp_path: Path, refs: dict, capfd: pytest.CaptureFixture[str]
) -> None:
    specs = cases(tmp_path / "runs", refs)
    spec_file = tmp_path / "cases.json"
    spec_file.write_text(
        json.dumps({"project": str(PROJECT), "warm_up": str(tmp_path / "warm"), "cases": specs})
    )
    threads = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    env = dict(os.environ, PYTHONPATH=str(ROOT), **threads)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, str(HARNESS), str(spec_file)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    harness_s = time.perf_counter() - t0
    results = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert len(results) == len(specs)
    new_project = load_project(PROJECT)
    outcomes = []
    for case in results:
        out = Path(case["out"])
        log = Path(case["log"]).read_text()
        assert "Traceback" not in log, log
        killed = case["signal"] == "SIGKILL"
        if case.get("delay") is None:
            assert case["exit"] == (-signal.SIGKILL if killed else 128 + signal.SIGTERM), case
        else:
            assert case["exit"] in (0, -signal.SIGKILL, -signal.SIGTERM, 143), case
        after = state(out, refs)
        assert after in expected_after_kill(case), (case, after)
        outcomes.append((case.get("point") or f"{case['delay']:.3f} s", case["signal"], after))
        leftovers = sorted(p.name for p in out.parent.iterdir() if p.name != "out")
        if not killed:
            assert leftovers == [], f"SIGTERM must clean up: {case} left {leftovers}"

        capfd.readouterr()
        next_run_that_fails(out)
        note = capfd.readouterr().err
        if after == "absent" and case["initial"] == "old":
            after = "old"
            assert "restored the previous output" in note
        assert state(out, refs) == after
        assert sorted(p.name for p in out.parent.iterdir()) == (
            ["out"] if after != "absent" else []
        )
        if any(n.startswith(".out.staging-") or n.startswith(".out.previous-") for n in leftovers):
            assert "left by interrupted runs" in note, (case, leftovers, note)

        run_build(new_project, out)
        assert state(out, refs) == "new"
        assert sorted(p.name for p in out.parent.iterdir()) == ["out"]
    elapsed = time.perf_counter() - t0
    print(f"{len(results)} kill cases in {elapsed:.1f} s (kills {harness_s:.1f} s)")
    assert {o[2] for o in outcomes} == {"old", "new", "absent"}


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGKILL"])
def test_kill_a_real_build_while_it_writes(tmp_path: Path, refs: dict, sig: str) -> None:
    out = tmp_path / "out"
    put_old(out, refs)
    env = dict(os.environ, COLUMNS="200", NO_COLOR="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "fabflow", "build", str(PROJECT), "-o", str(out)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    deadline = time.monotonic() + 120
    while not any(p.name.startswith(".out.staging-") for p in tmp_path.iterdir()):
        assert proc.poll() is None and time.monotonic() < deadline, "the build never staged"
        time.sleep(0.002)
    proc.send_signal(getattr(signal, sig))
    _, stderr = proc.communicate(timeout=60)
    assert "Traceback" not in stderr
    if proc.returncode == 0:  # it finished first
        assert state(out, refs) == "new"
        return
    assert proc.returncode == (143 if sig == "SIGTERM" else -signal.SIGKILL)
    assert state(out, refs) == "old"
    left = sorted(p.name for p in tmp_path.iterdir() if p.name != "out")
    if sig == "SIGTERM":
        assert left == []
        return
    assert any(n.startswith(".out.staging-") for n in left)
    again = subprocess.run(
        [sys.executable, "-m", "fabflow", "build", str(PROJECT), "-o", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
        check=False,
    )
    assert again.returncode == 0, again.stderr
    assert "left by interrupted runs" in again.stdout + again.stderr
    assert state(out, refs) == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
