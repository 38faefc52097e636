"""Paths and helpers shared by the tests (importable as ``helpers`` from any test folder)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

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


SMALL_STONE_WALL = """\
name: small_stone_wall
robot:
  model: excavator_gripper
  tool:
    name: two-jaw gripper
    T_flange_tool: {xyz: [0.0, 0.0, 0.95]}
    mass: 800.0
    cog: [0.0, 0.0, 0.35]
  platform: {footprint: [3.0, 2.4], lift: [0.0, 0.0], T_platform_base: {xyz: [0, 0, 0]}}
elements:
  - stone_wall:
      stockpile: {seed: 3, n_stones: 3, region_min: [2.0, -3.5], region_max: [5.5, 3.5]}
      slots:
        - {id: A, pose: {xyz: [-4.2, -0.9, 0.45], abc_deg: [90, 0, 0]}, size: [1.6, 1.25, 0.9]}
        - {id: B, pose: {xyz: [-4.2, 0.9, 0.45], abc_deg: [90, 0, 0]}, size: [1.5, 1.2, 0.9]}
      swing_deg: [-180, 160]
      swing_step_deg: 20
program: {format: json}
simulation: {robot_repeatability: 0.013}
"""
"""A stone wall of two slots from three stones: the stone pipeline in a few seconds."""


def small_stone_wall(folder: Path) -> Path:
    """Write :data:`SMALL_STONE_WALL` as ``folder/project.yaml`` and return its path."""
    path = folder / "project.yaml"
    path.write_text(SMALL_STONE_WALL, encoding="utf-8")
    return path


def icp_room(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points on the six walls of a 6 x 4 x 3 m room and on a round column (ICP tests)."""
    size = np.array([6.0, 4.0, 3.0])
    parts = []
    for axis in range(3):
        for value in (0.0, size[axis]):
            q = rng.uniform(0, 1, (n, 3)) * size
            q[:, axis] = value
            parts.append(q)
    u = rng.uniform(0, 1, (n, 2))
    th = 2 * np.pi * u[:, 0]
    parts.append(np.c_[2 + 0.3 * np.cos(th), 1.5 + 0.3 * np.sin(th), 3 * u[:, 1]])
    return np.vstack(parts)
