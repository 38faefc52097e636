"""The viser scene of a :class:`~fabflow.preview.model.PreviewModel`.

Every mesh is sent once, when the scene is built. Moving to another step
(:meth:`PreviewScene.set_step`) or changing the colour mode only updates
instance scales (visibility), instance colours and node poses: all blocks are
one batched mesh, and a block is hidden by giving its instance a zero scale.
"""

from __future__ import annotations

import threading

import numpy as np
import trimesh
import viser

from fabflow.errors import InputError
from fabflow.preview.model import STATION_PALETTE, PreviewModel
from fabflow.preview.site_sensors import add_localization
from fabflow.project import Project
from fabflow.transforms.so3 import quat_from_matrix

BLOCK_GAP = 0.003
"""Blocks are drawn this much smaller (metres) so neighbouring blocks read as separate."""
GHOST_COLOUR = (205, 210, 218)
GHOST_OPACITY = 0.18
ARM_COLOUR = (255, 112, 0)
JOINT_COLOUR = (60, 60, 66)
PLATFORM_COLOUR = (74, 80, 92)
LINK_RADIUS = 0.07


def _quat_z_to(directions: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z) turning +z onto each unit direction (N, 3)."""
    d = directions
    q = np.stack([1.0 + d[:, 2], -d[:, 1], d[:, 0], np.zeros(len(d))], axis=1)
    norm = np.linalg.norm(q, axis=1)
    flipped = norm < 1e-12  # d = -z: half a turn about x
    q[flipped] = (0.0, 1.0, 0.0, 0.0)
    norm[flipped] = 1.0
    return q / norm[:, None]


def _wxyz(T: np.ndarray) -> np.ndarray:
    return quat_from_matrix(np.asarray(T, dtype=float)[..., :3, :3])


class PreviewScene:
    """The construction sequence of one project, drawn on a viser server.

    Parameters
    ----------
    server
        The viser server to draw on (live, or used only to record an export).
    model
        The precomputed preview model.
    project
        The project, for the site (grid, obstacles) and the localization setup
        (UWB anchors, total station, ICP map); omitted parts are not drawn.
    colour_mode
        Initial colour mode (see :data:`~fabflow.preview.model.COLOUR_MODES`).
    ghost
        Show the elements not built yet as a faint ghost.
    step
        Initial step (``None``: the last step, the finished building).
    """

    def __init__(
        self,
        server: viser.ViserServer,
        model: PreviewModel,
        project: Project | None = None,
        colour_mode: str = "station",
        ghost: bool = True,
        step: int | None = None,
    ) -> None:
        if colour_mode not in model.colour_modes():
            raise InputError(
                f"colour mode '{colour_mode}' is not available; expected one of "
                f"{model.colour_modes()}"
            )
        self.server = server
        self.model = model
        self.colour_mode = colour_mode
        self.ghost_enabled = ghost
        self.step = model.n_steps if step is None else model.check_step(step)
        self._colour_cache: dict[str, np.ndarray] = {}
        # The play thread and browser callbacks may update the scene concurrently.
        self._lock = threading.RLock()
        self._visible = model.visible(self.step)
        self._draw_extents = np.maximum(model.block_extents - BLOCK_GAP, 1e-4).astype(np.float32)
        self._precompute_poses()
        scene = server.scene
        scene.set_up_direction("+z")
        with server.atomic():
            self._add_site(project)
            self._add_design()
            self._add_stations()
            self._add_platform_and_arm()
            if project is not None:
                add_localization(server.scene, project, model)
            self._add_results()
            self._set_camera(project)
        self.set_step(self.step, force=True)

    # ------------------------------------------------------------------ building

    def _add_site(self, project: Project | None) -> None:
        scene = self.server.scene
        lo, hi = self._bounds_xy(project)
        size = hi - lo
        centre = (lo + hi) / 2
        self.grid = scene.add_grid(
            "/site/grid",
            width=float(size[0]),
            height=float(size[1]),
            cell_size=0.5,
            section_size=1.0,
            position=(float(centre[0]), float(centre[1]), 0.0),
            plane_color=(244, 242, 236),
            plane_opacity=1.0,
            shadow_opacity=0.2,
        )
        if project is None:
            return
        for i, obstacle in enumerate(project.site.obstacles):
            if obstacle.box is not None:
                b = obstacle.box
                mn, mx = np.array(b.min), np.array(b.max)
                scene.add_box(
                    f"/site/obstacles/{i}_{b.name}",
                    color=(120, 120, 128),
                    dimensions=tuple(mx - mn),
                    position=tuple((mn + mx) / 2),
                    opacity=0.6,
                )
            elif obstacle.polygon is not None:
                poly = obstacle.polygon
                vertices, faces = _prism(
                    np.asarray(poly.points, dtype=float), poly.z_max - poly.z_min
                )
                scene.add_mesh_simple(
                    f"/site/obstacles/{i}_{poly.name}",
                    vertices=vertices,
                    faces=faces,
                    color=(120, 120, 128),
                    opacity=0.6,
                    flat_shading=True,
                    side="double",
                    position=(0.0, 0.0, poly.z_min),
                )

    def _bounds_xy(self, project: Project | None) -> tuple[np.ndarray, np.ndarray]:
        pts = [self.model.block_positions[:, :2], self.model.T_world_platform[:, :2, 3]]
        pts += [p[:, :2] for p in self.model.path_points]
        stacked = np.concatenate([np.asarray(p, dtype=float).reshape(-1, 2) for p in pts])
        if project is not None:
            lo = np.array(project.site.extent_min, dtype=float)
            hi = np.array(project.site.extent_max, dtype=float)
        elif stacked.size:
            lo, hi = stacked.min(axis=0) - 3.0, stacked.max(axis=0) + 3.0
        else:
            lo, hi = np.array([-5.0, -5.0]), np.array([5.0, 5.0])
        return np.floor(lo), np.ceil(hi)

    def _add_design(self) -> None:
        scene = self.server.scene
        m = self.model
        box = trimesh.creation.box((1.0, 1.0, 1.0))
        colours = self._colours(self.colour_mode, self.step)
        self.blocks = scene.add_batched_meshes_simple(
            "/design/blocks",
            vertices=box.vertices,
            faces=box.faces,
            batched_wxyzs=m.block_wxyz,
            batched_positions=m.block_positions,
            batched_scales=self._draw_extents,
            batched_colors=colours[m.block_index],
            flat_shading=True,
            lod="off",
        )
        self.ghost = scene.add_batched_meshes_simple(
            "/design/ghost",
            vertices=box.vertices,
            faces=box.faces,
            batched_wxyzs=m.block_wxyz,
            batched_positions=m.block_positions,
            batched_scales=self._draw_extents,
            batched_colors=GHOST_COLOUR,
            opacity=GHOST_OPACITY,
            flat_shading=True,
            cast_shadow=False,
            receive_shadow=False,
            lod="off",
            visible=self.ghost_enabled,
        )
        self.paths: list[viser.LineSegmentsHandle] = []
        for idx, pts in zip(m.path_index, m.path_points, strict=True):
            e = m.elements[idx]
            seg = np.stack([pts[:-1], pts[1:]], axis=1) if len(pts) > 1 else np.zeros((0, 2, 3))
            width = float(e.attributes.get("bead_width", 0.02))
            self.paths.append(
                scene.add_line_segments(
                    f"/design/paths/{e.id}",
                    points=seg.astype(np.float32),
                    colors=tuple(int(c) for c in colours[idx]),
                    thickness=width,
                    thickness_units="world",
                )
            )
        self.task_points = None
        if m.point_index.size:
            self.task_points = scene.add_batched_axes(
                "/design/task_points",
                batched_wxyzs=m.point_wxyz,
                batched_positions=m.point_positions,
                batched_scales=np.ones(m.point_index.size, dtype=np.float32),
                axes_length=0.08,
                axes_radius=0.006,
            )

    def _add_stations(self) -> None:
        scene = self.server.scene
        m = self.model
        first = [int(np.flatnonzero(m.package_station == s)[0]) for s in range(len(m.station_ids))]
        T = m.T_world_platform[first] if first else np.zeros((0, 4, 4))
        if not first:
            return
        scene.add_batched_axes(
            "/stations/frames",
            batched_wxyzs=_wxyz(T),
            batched_positions=T[:, :3, 3],
            axes_length=0.4,
            axes_radius=0.015,
        )
        for s, sid in enumerate(m.station_ids):
            scene.add_label(
                f"/stations/labels/{sid}",
                text=sid,
                position=tuple(T[s, :3, 3] + (0.0, 0.0, 0.05)),
            )
        # every station's footprint on the ground, in its station colour
        hx, hy = (v / 2 for v in m.platform.footprint)
        corners = np.array([[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]])
        world = np.einsum("sij,kj->ski", T[:, :3, :3], corners) + T[:, None, :3, 3]
        world[..., 2] += 0.005
        segments = np.stack([world, np.roll(world, -1, axis=1)], axis=2).reshape(-1, 2, 3)
        colours = np.repeat(STATION_PALETTE[np.arange(len(T)) % len(STATION_PALETTE)], 4, axis=0)
        scene.add_line_segments(
            "/stations/footprints",
            points=segments.astype(np.float32),
            colors=np.repeat(colours[:, None, :], 2, axis=1),
            thickness=0.015,
        )

    def _add_platform_and_arm(self) -> None:
        scene = self.server.scene
        m = self.model
        pf = m.platform
        base_z = float(pf.T_platform_base.xyz[2])
        body_h = max(0.15, min(0.5, 0.6 * base_z))
        length, width = pf.footprint
        self.platform = scene.add_frame("/platform", show_axes=False)
        scene.add_box(
            "/platform/body",
            color=PLATFORM_COLOUR,
            dimensions=(length, width, body_h),
            position=(0.0, 0.0, body_h / 2),
        )
        margin = pf.safety_margin
        hx, hy = length / 2 + margin, width / 2 + margin
        corners = np.array([[-hx, -hy, 0.01], [hx, -hy, 0.01], [hx, hy, 0.01], [-hx, hy, 0.01]])
        scene.add_line_segments(
            "/platform/safety_margin",
            points=np.stack([corners, np.roll(corners, -1, axis=0)], axis=1).astype(np.float32),
            colors=(230, 170, 30),
            thickness=0.02,
        )
        T_pb = pf.T_platform_base.matrix()
        self._lift_xy = T_pb[:2, 3]
        self._body_h = body_h
        self.lift = scene.add_box(
            "/platform/lift",
            color=(150, 156, 168),
            dimensions=(0.35, 0.35, 1.0),
            position=(float(self._lift_xy[0]), float(self._lift_xy[1]), body_h + 0.5),
        )

        n_links = max(m.arm_points.shape[1] - 1, 0)
        self.arm_links = None
        self.arm_joints = None
        if n_links:
            cyl = trimesh.creation.cylinder(radius=1.0, height=1.0, sections=20)
            self.arm_links = scene.add_batched_meshes_simple(
                "/arm/links",
                vertices=cyl.vertices,
                faces=cyl.faces,
                batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (n_links, 1)),
                batched_positions=np.zeros((n_links, 3)),
                batched_scales=np.ones((n_links, 3)),
                batched_colors=ARM_COLOUR,
                lod="off",
            )
            sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
            self.arm_joints = scene.add_batched_meshes_simple(
                "/arm/joints",
                vertices=sphere.vertices,
                faces=sphere.faces,
                batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (n_links + 1, 1)),
                batched_positions=np.zeros((n_links + 1, 3)),
                batched_scales=np.full(n_links + 1, LINK_RADIUS * 1.25),
                batched_colors=JOINT_COLOUR,
                lod="off",
            )
        self.tool = scene.add_frame("/arm/tool", axes_length=0.15, axes_radius=0.008)
        self.target_warning = scene.add_label(
            "/arm/tool/unreachable", text="target not reachable", visible=False
        )

    def _add_results(self) -> None:
        """Localized base frames and measured points, shown for the current visit only."""
        scene = self.server.scene
        self._results: list[tuple[int | str, viser.FrameHandle]] = []
        for key, result in self.model.localization.items():
            T = np.asarray(result.T_world_base, dtype=float)
            name = f"visit_{key + 1}" if isinstance(key, int) else str(key)
            integ = result.integrity
            bad = integ is None or integ.failed or bool(integ.checks.get("degraded"))
            frame = scene.add_frame(
                f"/localization/results/{name}",
                axes_length=0.35,
                axes_radius=0.012,
                # a failed or degraded localization is marked red
                origin_color=(220, 0, 0) if bad else (200, 40, 160),
                wxyz=tuple(_wxyz(T)),
                position=tuple(T[:3, 3]),
                visible=False,
            )
            points = np.asarray(result.quality.get("points_world", ()), dtype=float)
            if points.ndim == 2 and points.shape[1] == 3 and len(points):
                # prism points measured by the total station, drawn in the world
                T_frame_world = np.linalg.inv(T)
                local = points @ T_frame_world[:3, :3].T + T_frame_world[:3, 3]
                scene.add_point_cloud(
                    f"/localization/results/{name}/prisms",
                    points=local.astype(np.float32),
                    colors=(240, 200, 0),
                    point_size=0.05,
                    point_shape="diamond",
                )
            self._results.append((key, frame))

    def _set_camera(self, project: Project | None) -> None:
        m = self.model
        pts = [m.block_positions, *m.path_points, m.T_world_platform[:, :3, 3]]
        stacked = np.concatenate([np.asarray(p, dtype=float).reshape(-1, 3) for p in pts])
        if stacked.size == 0:
            stacked = np.zeros((1, 3))
        lo, hi = stacked.min(axis=0), stacked.max(axis=0)
        centre = (lo + hi) / 2
        radius = max(float(np.linalg.norm(hi - lo)) / 2, 1.0)
        direction = np.array([-0.55, -1.0, 0.7])
        direction /= np.linalg.norm(direction)
        cam = self.server.initial_camera
        cam.up = (0.0, 0.0, 1.0)
        cam.look_at = tuple(centre)
        cam.position = tuple(centre + direction * radius * 1.9)

    # ------------------------------------------------------------------ updates

    def _colours(self, mode: str, step: int) -> np.ndarray:
        if mode == "state":
            return self.model.element_colours(mode, step)
        if mode not in self._colour_cache:
            self._colour_cache[mode] = self.model.element_colours(mode, step)
        return self._colour_cache[mode]

    def _precompute_poses(self) -> None:
        """Per-package platform quaternions and per-step tool and arm-link poses."""
        m = self.model
        self._platform_wxyz = _wxyz(m.T_world_platform).reshape(-1, 4)
        self._tool_wxyz = _wxyz(m.T_world_tool).reshape(-1, 4)
        pts = m.arm_points
        seg = pts[:, 1:] - pts[:, :-1]
        length = np.linalg.norm(seg, axis=2)
        direction = seg / np.maximum(length, 1e-9)[..., None]
        radius = np.where(length > 1e-6, LINK_RADIUS, 0.0)
        self._link_positions = ((pts[:, 1:] + pts[:, :-1]) / 2).astype(np.float32)
        self._link_wxyz = _quat_z_to(direction.reshape(-1, 3)).reshape(*direction.shape[:2], 4)
        self._link_scales = np.stack([radius, radius, length], axis=2).astype(np.float32)
        self._package: int | None = None

    def set_step(self, step: int, force: bool = False) -> None:
        """Show the scene after ``step`` placements (poses, visibility, colours only).

        Parameters
        ----------
        step
            0..n_steps.
        force
            Send every per-step property even if unchanged.
        """
        m = self.model
        step = m.check_step(step)
        visible = m.visible(step)
        with self._lock, self.server.atomic():
            changed = force or not np.array_equal(visible, self._visible)
            if changed:
                vb = visible[m.block_index]
                self.blocks.batched_scales = self._draw_extents * vb[:, None]
                self.ghost.batched_scales = self._draw_extents * ~vb[:, None]
                for handle, idx in zip(self.paths, m.path_index, strict=True):
                    handle.visible = bool(visible[idx])
                if self.task_points is not None:
                    self.task_points.batched_scales = visible[m.point_index].astype(np.float32)
            if force or self.colour_mode == "state":
                self._apply_colours(self._colours(self.colour_mode, step))
            self._pose_platform_and_arm(step, force)
            self._visible = visible
            self.step = step

    def _pose_platform_and_arm(self, step: int, force: bool) -> None:
        m = self.model
        p = m.package_at(step)
        if p < 0:
            return
        if force or p != self._package:
            T = m.T_world_platform[p]
            self.platform.position = tuple(T[:3, 3])
            self.platform.wxyz = tuple(self._platform_wxyz[p])
            base_z = float(m.platform.T_platform_base.xyz[2]) + float(m.lift[p])
            column = max(base_z - self._body_h, 0.01)
            self.lift.scale = (1.0, 1.0, column)
            self.lift.position = (
                float(self._lift_xy[0]),
                float(self._lift_xy[1]),
                self._body_h + column / 2,
            )
            station = m.station_ids[int(m.package_station[p])]
            for key, frame in self._results:
                frame.visible = key == p or key == station
            self._package = p
        if self.arm_links is not None and self.arm_joints is not None:
            self.arm_links.batched_positions = self._link_positions[step]
            self.arm_links.batched_wxyzs = self._link_wxyz[step]
            self.arm_links.batched_scales = self._link_scales[step]
            self.arm_joints.batched_positions = m.arm_points[step]
        self.tool.position = tuple(m.T_world_tool[step, :3, 3])
        self.tool.wxyz = tuple(self._tool_wxyz[step])
        self.target_warning.visible = not bool(m.arm_reached[step])

    def _apply_colours(self, colours: np.ndarray) -> None:
        m = self.model
        self.blocks.batched_colors = colours[m.block_index]
        for handle, idx in zip(self.paths, m.path_index, strict=True):
            if not np.array_equal(handle.colors, colours[idx]):
                handle.colors = colours[idx].copy()

    def set_colour_mode(self, mode: str) -> None:
        """Recolour the elements (colours only; nothing else is sent)."""
        if mode not in self.model.colour_modes():
            raise InputError(
                f"colour mode '{mode}' is not available; expected one of "
                f"{self.model.colour_modes()}"
            )
        with self._lock, self.server.atomic():
            self.colour_mode = mode
            self._apply_colours(self._colours(mode, self.step))

    def set_ghost(self, enabled: bool) -> None:
        """Show or hide the faint ghost of the elements not built yet."""
        self.ghost_enabled = bool(enabled)
        self.ghost.visible = self.ghost_enabled

    def station_colour(self, station_id: str) -> tuple[int, int, int]:
        """The colour a station has in the ``station`` colour mode."""
        s = self.model.station_ids.index(station_id)
        return tuple(int(c) for c in STATION_PALETTE[s % len(STATION_PALETTE)])  # type: ignore[return-value]


def _prism(points: np.ndarray, height: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a plan polygon (K, 2) extruded from z = 0 to ``height``.

    The caps are a constrained Delaunay triangulation, so concave outlines work.
    """
    import shapely

    polygon = shapely.Polygon(points)
    if not polygon.is_valid:
        polygon = shapely.make_valid(polygon)
    triangles = shapely.get_parts(shapely.constrained_delaunay_triangles(polygon))
    tri_xy = np.array([np.asarray(t.exterior.coords)[:3] for t in triangles]).reshape(-1, 2)
    n_tri = len(tri_xy) // 3
    ring = np.asarray(points, dtype=float)
    K = len(ring)
    vertices = np.concatenate(
        [
            np.c_[tri_xy, np.zeros(len(tri_xy))],
            np.c_[tri_xy, np.full(len(tri_xy), height)],
            np.c_[ring, np.zeros(K)],
            np.c_[ring, np.full(K, height)],
        ]
    )
    caps = np.arange(6 * n_tri).reshape(-1, 3)
    b = 6 * n_tri
    i = np.arange(K)
    j = (i + 1) % K
    sides = np.concatenate([np.c_[b + i, b + j, b + K + j], np.c_[b + i, b + K + j, b + K + i]])
    return vertices, np.concatenate([caps, sides]).astype(np.int32)
