"""Paths and helpers shared by the tests (importable as ``helpers`` from any test folder)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROJECTS = ROOT / "projects"
DATA = ROOT / "tests" / "data"
TS_DATA = DATA / "total_station"
"""Sample total station readings (see its README.md)."""


def run_cli(
    *args: str, cwd: Path | None = None, timeout: float = 300
) -> subprocess.CompletedProcess:
    """Run ``fabflow ARGS`` in a subprocess, as a user would, and capture its output."""
    env = dict(os.environ, COLUMNS="200", NO_COLOR="1")
    return subprocess.run(
        [sys.executable, "-m", "fabflow", *args],
        cwd=cwd or ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        check=False,
    )
