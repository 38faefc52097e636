"""Every benchmark script runs (in its --quick form) and prints a table.

The figures themselves are read by people; this keeps the scripts from rotting.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from helpers import ROOT

SCRIPTS = sorted(p for p in (ROOT / "benchmarks").glob("*.py") if not p.name.startswith("_"))
"""Every benchmark script; ``_name.py`` modules are shared code the scripts import."""


def test_every_area_has_a_benchmark() -> None:
    names = {p.stem for p in SCRIPTS}
    assert {
        "transforms",
        "design",
        "kinematics",
        "plan",
        "total_station",
        "registration",
        "icp",
        "uwb",
        "programs",
        "preview",
        "simulate",
        "stones",
        "tracking",
        "link",
        "startup",
        "build",
    } <= names


@pytest.mark.slow
@pytest.mark.parametrize("script", SCRIPTS, ids=[p.stem for p in SCRIPTS])
def test_benchmark_quick(script, tmp_path) -> None:
    result = subprocess.run(
        [sys.executable, str(script), "--quick"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    lines = [line for line in result.stdout.splitlines() if line.strip()]
    assert len(lines) >= 3, result.stdout
