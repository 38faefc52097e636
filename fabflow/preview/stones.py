"""The preview of a stone wall build: one offline HTML file.

The recording starts with the LiDAR map (grey) and the found objects, each in
its own colour, the slots of the wall as faint boxes. Then, per slot, two steps:
the grasp candidates as gripper glyphs (a U: the two jaws and the palm) with the
chosen grasp drawn as the gripper, green when the simulated grasp held and red
when it did not; then the stone set in its slot and the slot box filled.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import viser

from fabflow.manipulation.gripper import TwoJawGripper, gripper_mesh
from fabflow.preview.export import ExportResult, check_export_target, quiet_server, write_atomic
from fabflow.project import Project
from fabflow.stones.run import StoneRun
from fabflow.transforms.se3 import apply_T, inv_T
from fabflow.transforms.so3 import quat_from_matrix

MAP_COLOUR = (150, 150, 150)
SLOT_COLOUR = (90, 140, 220)
CANDIDATE_COLOUR = (240, 190, 40)
HELD_COLOUR = (40, 170, 70)
DROPPED_COLOUR = (210, 50, 40)
MAX_GLYPHS = 20
"""Grasp candidates drawn per pick (the best ranked)."""


def _colours(n: int) -> np.ndarray:
    """``(n, 3)`` distinct uint8 colours (golden-ratio hues)."""
    h = (np.arange(n) * 0.618034) % 1.0
    k = (np.array([5.0, 3.0, 1.0])[None] + 6.0 * h[:, None]) % 6.0
    rgb = 1.0 - 0.75 * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return (255 * rgb).astype(np.uint8)


def _glyphs(T: np.ndarray, opening: np.ndarray, gripper: TwoJawGripper) -> np.ndarray:
    """``(3K, 2, 3)`` line segments of K gripper glyphs (gripper frames ``(K, 4, 4)``)."""
    half, depth = 0.5 * np.asarray(opening, dtype=float), gripper.jaw_length
    zeros = np.zeros_like(half)
    a = np.stack([zeros, half, zeros], axis=1)
    b = np.stack([zeros, half, zeros - depth], axis=1)
    c = np.stack([zeros, -half, zeros - depth], axis=1)
    d = np.stack([zeros, -half, zeros], axis=1)
    local = np.stack([a, b, b, c, c, d], axis=1)  # (K, 6, 3)
    world = np.einsum("kij,knj->kni", T[:, :3, :3], local) + T[:, None, :3, 3]
    return world.reshape(-1, 2, 3)


def _pose(handle: viser.FrameHandle, T: np.ndarray) -> None:
    handle.wxyz = tuple(float(v) for v in quat_from_matrix(T[:3, :3]))
    handle.position = tuple(float(v) for v in T[:3, 3])


def _record(server: viser.ViserServer, run: StoneRun, project: Project, dt: float) -> str:
    scene = server.scene
    gripper = TwoJawGripper()
    scene.add_point_cloud(
        "/map",
        points=run.perception.map_points.astype(np.float32),
        colors=MAP_COLOUR,
        point_size=0.02,
    )
    first = run.perception.db
    colours = _colours(len(first))
    frames: dict[int, viser.FrameHandle] = {}
    for obj, colour in zip(first.objects, colours, strict=True):
        frame = scene.add_frame(f"/objects/{obj.id}", show_axes=False)
        _pose(frame, obj.history[0].T_world_object)
        scene.add_point_cloud(
            f"/objects/{obj.id}/points",
            points=obj.points.astype(np.float32),
            colors=tuple(int(c) for c in colour),
            point_size=0.03,
        )
        frames[obj.id] = frame
    spec = project.stone_wall()
    assert spec is not None
    boxes = {}
    for slot in spec.slots:
        T = slot.pose.matrix()
        boxes[slot.id] = scene.add_box(
            f"/slots/{slot.id}",
            color=SLOT_COLOUR,
            dimensions=slot.size,
            wxyz=tuple(float(v) for v in quat_from_matrix(T[:3, :3])),
            position=tuple(float(v) for v in T[:3, 3]),
            opacity=0.25,
        )
    centre = run.perception.map_points.mean(axis=0)
    scene.add_label(
        "/legend",
        text=project.name,
        position=tuple(float(v) for v in centre + np.array([0.0, 0.0, 3.0])),
    )
    serializer = server.get_scene_serializer()
    serializer.insert_sleep(1.0)
    for k, pick in enumerate(run.picks):
        if pick.plan is None or pick.T_grasp is None:
            continue
        grasps = pick.plan.grasps
        shown = pick.plan.ranking[:MAX_GLYPHS]
        glyphs = scene.add_line_segments(
            f"/grasps/{k}/candidates",
            points=_glyphs(grasps.T_world_gripper[shown], grasps.opening[shown], gripper).astype(
                np.float32
            ),
            colors=CANDIDATE_COLOUR,
            thickness=0.01,
        )
        mesh = gripper_mesh(gripper, pick.opening)
        held = pick.outcome is not None and pick.outcome.success
        chosen = scene.add_mesh_simple(
            f"/grasps/{k}/chosen",
            vertices=apply_T(pick.T_grasp, mesh.vertices).astype(np.float32),
            faces=np.asarray(mesh.faces, dtype=np.uint32),
            color=HELD_COLOUR if held else DROPPED_COLOUR,
            opacity=0.7,
        )
        serializer.insert_sleep(dt)
        glyphs.visible = False
        chosen.visible = False
        assert pick.T_release is not None and pick.T_object is not None
        _pose(frames[pick.object_id], pick.T_release @ inv_T(pick.T_grasp) @ pick.T_object)
        boxes[pick.slot].visible = False
        serializer.insert_sleep(dt)
    serializer.insert_sleep(2.0)
    return serializer.as_html()


def export_stone_html(
    run: StoneRun, path: str | Path, project: Project, seconds_per_step: float = 1.5
) -> ExportResult:
    """Write the stone wall's preview as one self-contained HTML file (module docstring).

    Parameters
    ----------
    run
        The stone wall run.
    path
        Target ``.html`` file (written whole or not at all).
    project
        The project (its name and the wall's slots).
    seconds_per_step
        Playback time per step (seconds).
    """
    target = check_export_target(path)
    with quiet_server() as server, server.atomic():
        text = _record(server, run, project, seconds_per_step)
    data = text.encode("utf-8")
    write_atomic(target, data)
    n_steps = 2 * sum(p.T_grasp is not None for p in run.picks)
    return ExportResult(
        path=target,
        size_bytes=len(data),
        n_steps=n_steps,
        duration_s=1.0 + seconds_per_step * n_steps + 2.0,
        seconds_per_step=seconds_per_step,
    )
