"""End to end: the cabin's programs reproduce every block's world pose.

``fabflow build`` writes one KRL program per work package. Reading every
``.dat`` back, the place target of each robot-built block, put through the
station's localized base pose, must equal the block's design tool target within
0.01 mm and 0.001 deg.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from program_readers import program_files, read_krl

from fabflow.build.context import BuildContext
from fabflow.design.elements import elements_from_json
from fabflow.tasks.targets import element_tool_frames


def _angle_deg(R: np.ndarray, R_ref: np.ndarray) -> float:
    cos = np.clip((np.trace(R.T @ R_ref) - 1) / 2, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)))


def test_every_station_has_a_program(cabin_build: tuple[Path, BuildContext]) -> None:
    cabin_build, _ = cabin_build
    plan = json.loads((cabin_build / "plan.json").read_text())
    packages = [wp for wp in plan["work_packages"] if wp["elements"]]
    mains = [p for p in (cabin_build / "programs").glob("*.src") if "_P0" not in p.stem[-4:]]
    assert len(mains) == len(packages)
    stations = {wp["station"]["id"] for wp in packages}
    for sid in stations:
        assert any(p.stem.endswith(sid) for p in mains), sid


def test_place_targets_reproduce_block_poses(cabin_build: tuple[Path, BuildContext]) -> None:
    cabin_build, _ = cabin_build
    doc = json.loads((cabin_build / "elements.json").read_text())
    elements = elements_from_json(doc["elements"])
    by_id = {e.id: e for e in elements}
    plan = json.loads((cabin_build / "plan.json").read_text())
    placed: dict[str, np.ndarray] = {}
    for wp in plan["work_packages"]:
        if not wp["elements"]:
            continue
        visit, sid = wp["index"] + 1, wp["station"]["id"]
        loc = json.loads(
            (cabin_build / "localization" / f"visit_{visit:02d}_{sid}.json").read_text()
        )
        T_world_base = np.array(loc["T_world_base"])
        name = f"fab_v{visit:02d}_{sid}"
        read = read_krl(program_files(cabin_build / "programs", name))
        base = read.base
        np.testing.assert_allclose(base, np.linalg.inv(T_world_base), atol=1e-5)
        for _, T_in_base_frame, _, comment in read.moves:
            eid, _, label = comment.partition(" ")
            if label == "place":
                assert eid not in placed, f"{eid} placed twice"
                placed[eid] = T_world_base @ (base @ T_in_base_frame)
    robot_built = [e for e in elements if e.robot_built]
    assert sorted(placed) == sorted(e.id for e in robot_built)
    for eid, T in placed.items():
        T_ref = element_tool_frames(by_id[eid])[0]
        assert np.linalg.norm(T[:3, 3] - T_ref[:3, 3]) < 1e-5, eid
        assert _angle_deg(T[:3, :3], T_ref[:3, :3]) < 1e-3, eid


def test_programs_keep_their_configuration(cabin_build: tuple[Path, BuildContext]) -> None:
    """Issue 18's bar on the cabin as a user builds it (UWB-localized stations): no wide
    swing, at most one configuration change per work package, none inside a linear move."""
    _, ctx = cabin_build
    assert ctx.programs
    for program in ctx.programs:
        checks = program.checks
        assert checks["needless_swings"] == 0, (program.name, checks["swing_moves"])
        assert checks["configuration_changes"] <= 1, (program.name, checks["configurations"])
        assert checks["changes_inside_lin"] == 0, (program.name, checks["inside_lin_moves"])
