"""The files of a stone wall build: ``objects.json`` with one PLY per object, ``grasps.json``.

``objects.json``::

    {"frame": "world", "units": "m", "objects": [
        {"id": 0, "points": "objects/object_000.ply", "n_points": 1234,
         "extents_m": [...], "history": [
            {"event": "detected", "T_world_object": [[...]], "T_world_gripper": null},
            {"event": "grasp", ...}, {"event": "release", ...}, {"event": "detected", ...}]}]}

The PLY holds the object's model points in its own frame (metres); the history's
last pose places them in the world. ``grasps.json`` has one entry per slot: the
object, the chosen grasp's ``T_world_gripper`` (z the approach, y the closing
direction, origin midway between the jaws' tips), its ``opening_m`` and every
force-closure candidate with its costs and rank (``reachable`` tells whether the
machine reaches it, its release and their approaches); ``passed_over`` lists the
stones tried for the slot before it that had no reachable grasp, with the reason.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fabflow.manipulation.objects import ObjectDatabase, history_json
from fabflow.output import write_json
from fabflow.positioning.pointcloud_io import write_point_cloud
from fabflow.stones.run import PickResult


def _matrix(T: np.ndarray | None) -> list[list[float]] | None:
    return None if T is None else np.round(np.asarray(T, dtype=float), 9).tolist()


def write_objects(folder: Path, db: ObjectDatabase) -> Path:
    """Write ``objects.json`` and ``objects/object_NNN.ply`` into ``folder``."""
    (folder / "objects").mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    for obj in db.objects:
        name = f"objects/object_{obj.id:03d}.ply"
        write_point_cloud(folder / name, obj.points)
        rows.append(
            {
                "id": obj.id,
                "points": name,
                "n_points": len(obj.points),
                "extents_m": np.round(obj.extents, 6).tolist(),
                "history": history_json(obj),
            }
        )
    path = folder / "objects.json"
    write_json(path, {"frame": "world", "units": "m", "objects": rows})
    return path


def pick_json(pick: PickResult) -> dict[str, Any]:
    """One ``grasps.json`` entry (module docstring)."""
    row: dict[str, Any] = {
        "slot": pick.slot,
        "object": pick.object_id if pick.object_id >= 0 else None,
        "T_world_gripper": _matrix(pick.T_grasp),
        "opening_m": round(pick.opening, 6) if pick.T_grasp is not None else None,
        "T_world_gripper_release": _matrix(pick.T_release),
        "T_world_object_target": _matrix(pick.T_target),
    }
    if pick.reason:
        row["reason"] = pick.reason
    if pick.passed_over:
        row["passed_over"] = [{"object": i, "reason": why} for i, why in pick.passed_over]
    row["candidates"] = [] if pick.plan is None else pick.plan.candidate_rows()
    return row


def write_grasps(folder: Path, picks: list[PickResult]) -> Path:
    """Write ``grasps.json`` into ``folder``."""
    path = folder / "grasps.json"
    write_json(path, {"frame": "world", "units": "m", "picks": [pick_json(p) for p in picks]})
    return path
