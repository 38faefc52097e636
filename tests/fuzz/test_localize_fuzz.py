"""Fuzz: the ``fabflow localize`` computations on damaged files, in-process and as commands.

In-process, each example damages one input of a localization (the others stay the
valid samples): it returns a pose whose numbers are finite, or raises a user error
naming one of its files. A handful of subprocess runs of the commands check what a
user sees: exit code 0 or 2, no traceback, and no NaN or Infinity in the JSON written.
"""

from __future__ import annotations

import json
import random
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from helpers import DATA, TS_DATA
from hypothesis import given
from hypothesis import strategies as st
from reader_mutations import (
    LONG_FIELD,
    MAX_MESSAGE,
    REPLACEMENTS,
    all_finite,
    fuzz_settings,
    mutated,
    renumbered,
)

from fabflow.errors import FabflowError
from fabflow.json_format import json_safe
from fabflow.localize.icp import localize_files as localize_icp
from fabflow.localize.total_station import localize_files as localize_ts
from fabflow.localize.uwb_files import localize_from_files
from fabflow.positioning.pointcloud_io import write_point_cloud
from fabflow.transforms.se3 import apply_T, inv_T, make_T
from fabflow.transforms.so3 import exp_so3

STATIC = DATA / "uwb" / "static"
MOVING = DATA / "uwb" / "moving"


def _room(rng: np.random.Generator) -> np.ndarray:
    """Points on the floor and three walls of a 10 m x 8 m room with a pillar (metres)."""
    u = rng.uniform(0.0, 1.0, (6000, 2))
    floor = np.c_[u[:1500, 0] * 10, u[:1500, 1] * 8, np.zeros(1500)]
    wall_x = np.c_[np.zeros(1500), u[1500:3000, 0] * 8, u[1500:3000, 1] * 3]
    wall_y = np.c_[u[3000:4500, 0] * 10, np.full(1500, 8.0), u[3000:4500, 1] * 3]
    pillar = np.c_[6 + u[4500:, 0] * 0.5, 3.0 + 0 * u[4500:, 0], u[4500:, 1] * 3]
    return np.vstack([floor, wall_x, wall_y, pillar])


def _icp_samples() -> dict[str, bytes]:
    """A map (ASCII PLY, world frame) and a scan of it (XYZ, LiDAR frame) of the room."""
    rng = np.random.default_rng(3)
    world = _room(rng)
    T_world_lidar = make_T(exp_so3([0.0, 0.0, np.radians(20.0)]), [4.9, 4.0, 1.2])
    scan = apply_T(inv_T(T_world_lidar), _room(rng)) + rng.normal(0, 0.005, world.shape)
    with tempfile.TemporaryDirectory() as folder:
        write_point_cloud(Path(folder) / "map.ply", world, binary=False)
        write_point_cloud(Path(folder) / "scan.xyz", scan)
        return {name: (Path(folder) / name).read_bytes() for name in ("map.ply", "scan.xyz")}


ICP = _icp_samples()
SAMPLES: dict[str, tuple[str, bytes]] = {
    "ranges": (".csv", (STATIC / "ranges.csv").read_bytes()),
    "anchors": (".yaml", (STATIC / "anchors.yaml").read_bytes()),
    "moving_ranges": (".csv", (MOVING / "ranges.csv").read_bytes()),
    "moving_anchors": (".yaml", (MOVING / "anchors.yaml").read_bytes()),
    "imu": (".csv", (MOVING / "imu.csv").read_bytes()),
    "obs": (".csv", (TS_DATA / "obs.csv").read_bytes()),
    "gsi": (".gsi", (TS_DATA / "obs_gsi16.gsi").read_bytes()),
    "points": (".csv", (TS_DATA / "robot_points.csv").read_bytes()),
    "scan": (".xyz", ICP["scan.xyz"]),
    "map": (".ply", ICP["map.ply"]),
}
"""Valid inputs of the localizations: suffix and contents by name."""

Files = dict[str, Path]
CASES: dict[str, tuple[str, Callable[[Files], object]]] = {
    "uwb static": ("ranges", lambda f: localize_from_files(f["ranges"], f["anchors"])),
    "uwb anchors": ("anchors", lambda f: localize_from_files(f["ranges"], f["anchors"])),
    "uwb moving": (
        "imu",
        lambda f: localize_from_files(f["moving_ranges"], f["moving_anchors"], f["imu"]),
    ),
    "total station csv": ("obs", lambda f: localize_ts(f["obs"], f["points"])),
    "total station gsi": ("gsi", lambda f: localize_ts(f["gsi"], f["points"])),
    "robot points": ("points", lambda f: localize_ts(f["gsi"], f["points"])),
    "uwb moving ranges": (
        "moving_ranges",
        lambda f: localize_from_files(f["moving_ranges"], f["moving_anchors"], f["imu"]),
    ),
    "icp scan": ("scan", lambda f: localize_icp(f["scan"], f["map"], (4.9, 4.0, 20.0))),
    "icp map": ("map", lambda f: localize_icp(f["scan"], f["map"], (4.9, 4.0, 20.0))),
}
"""Which input each case damages, and the localization it runs."""


def _write_inputs(folder: Path, damaged: str | None = None, data: bytes = b"") -> Files:
    """The inputs written to ``folder``, ``damaged`` with ``data`` instead of its sample."""
    files = {}
    for name, (suffix, content) in SAMPLES.items():
        files[name] = folder / f"{name}{suffix}"
        files[name].write_bytes(data if name == damaged else content)
    return files


@st.composite
def damaged_inputs(draw: st.DrawFn) -> tuple[str, bytes]:
    name = draw(st.sampled_from(sorted(CASES)))
    sample = SAMPLES[CASES[name][0]][1]
    return name, draw(st.one_of(mutated(sample), renumbered(sample)))


@fuzz_settings(100)
@given(damaged_inputs())
def test_localize_on_a_damaged_file(case: tuple[str, bytes]) -> None:
    name, data = case
    which, run = CASES[name]
    with tempfile.TemporaryDirectory() as folder, warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # none may reach the user
        inputs = _write_inputs(Path(folder), which, data)
        try:
            pose = run(inputs)
        except FabflowError as exc:
            assert exc.exit_code == 2
            assert exc.source in {str(p) for p in inputs.values()}, f"no file named: {exc}"
            assert len(str(exc).replace(str(exc.source), "")) < MAX_MESSAGE
            return
    assert all_finite([pose.T_world_base, pose.covariance, pose.residuals, pose.rmse])
    json.dumps(json_safe(pose.to_dict()), allow_nan=False)


def _damage(data: bytes, rng: random.Random) -> bytes:
    """One seeded, plain damage for the command-line runs."""
    lines = data.split(b"\n")
    k = rng.randrange(1, max(len(lines) - 1, 2))
    kind = rng.choice(["number", "long", "truncate", "latin1"])
    if kind == "number":
        fields = lines[k].split(b",")
        fields[-1] = rng.choice(REPLACEMENTS)
        lines[k] = b",".join(fields)
    elif kind == "long":
        lines[k] += LONG_FIELD
    elif kind == "truncate":
        return data[: rng.randrange(len(data))]
    else:
        lines[k] += b"\xff\xfe"
    return b"\n".join(lines)


COMMANDS = [
    ("uwb", ["localize", "uwb", "{ranges}", "--anchors", "{anchors}"], "ranges"),
    ("uwb", ["localize", "uwb", "{ranges}", "--anchors", "{anchors}"], "anchors"),
    ("total-station", ["localize", "total-station", "{obs}", "--robot-points", "{points}"], "obs"),
    (
        "total-station",
        [
            "localize",
            "total-station",
            "{gsi}",
            "--robot-points",
            "{points}",
            "--robot-sigma",
            "inf",
        ],
        None,
    ),
    ("icp", ["localize", "icp", "{scan}", "--map", "{map}", "--init", "4.9,4.0,20"], "scan"),
    ("icp", ["localize", "icp", "{scan}", "--map", "{map}", "--init", "4.9,4.0,20"], "map"),
]


@pytest.mark.parametrize(("method", "args", "which"), COMMANDS)
def test_commands_on_damaged_files(
    cli, tmp_path: Path, method: str, args: list[str], which: str | None
) -> None:
    data = b""
    if which is not None:
        data = _damage(SAMPLES[which][1], random.Random(f"{method} {which}"))
    files = _write_inputs(tmp_path, which, data)
    out = tmp_path / "out"
    result = cli(*[a.format(**files) for a in args], "-o", str(out))
    assert result.returncode in (0, 2), result.stderr[-2000:]
    assert "Traceback" not in result.stderr and "Warning" not in result.stderr
    for written in out.rglob("*.json") if out.exists() else []:
        text = written.read_text()
        assert "NaN" not in text and "Infinity" not in text
        json.loads(text)
