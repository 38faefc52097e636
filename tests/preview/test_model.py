"""The preview scene in-process: steps, platform, arm, colour modes, updates, export."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.design.elements import Element
from fabflow.errors import InputError
from fabflow.positioning.result import BasePose
from fabflow.preview.app import LivePreview, serve
from fabflow.preview.arm import RobotArm
from fabflow.preview.gui import step_info, work_package_json
from fabflow.preview.model import COLOUR_MODES, build_model
from fabflow.preview.scene import PreviewScene
from fabflow.preview.synthetic import PointArm, translation, wall_design
from fabflow.robots import get_robot
from fabflow.tasks.plan import Plan, Station, WorkPackage

T_FLANGE_TOOL = translation(0.0, 0.0, 0.2)
POSE_PROPS = {"position", "wxyz", "scale", "batched_positions", "batched_wxyzs"}
VISIBILITY_PROPS = {"visible", "batched_scales"}
COLOUR_PROPS = {"batched_colors", "colors"}
UPDATE_KINDS = {
    "SceneNodeUpdateMessage",
    "SetPositionMessage",
    "SetOrientationMessage",
    "SetSceneNodeVisibilityMessage",
    "GuiUpdateMessage",
}


@pytest.fixture(scope="module")
def model():
    elements, plan = wall_design()
    deviation = {e.id: 0.004 * (i % 6) for i, e in enumerate(elements) if e.type == "block"}
    return build_model(
        elements,
        plan,
        name="wall",
        arm=PointArm(),
        T_flange_tool=T_FLANGE_TOOL,
        deviation=deviation,
        tolerance=0.01,
    )


@pytest.fixture(scope="module")
def live(model) -> Iterator[LivePreview]:
    preview = serve(model, port=0)
    yield preview
    preview.stop()


class MessageLog:
    """Records every message the server queues while active."""

    def __init__(self, server) -> None:
        self.server = server
        self.messages: list = []
        self._orig = None

    def __enter__(self) -> MessageLog:
        ws = self.server._websock_server
        self._orig = ws.queue_message

        def record(message) -> None:
            self.messages.append(message)
            self._orig(message)

        ws.queue_message = record
        return self

    def __exit__(self, *exc) -> None:
        self.server._websock_server.queue_message = self._orig

    def scene_props(self) -> set[str]:
        props: set[str] = set()
        for msg in self.messages:
            if type(msg).__name__ == "SceneNodeUpdateMessage":
                props |= set(msg.updates)
        return props

    def kinds(self) -> set[str]:
        return {type(m).__name__ for m in self.messages}


def visible_planned(model, scene: PreviewScene) -> list[str]:
    """Ids of the planned blocks drawn with a non-zero size, in build order."""
    shown = np.any(scene.blocks.batched_scales > 0, axis=1)
    ids = {model.elements[i].id for i, s in zip(model.block_index, shown, strict=True) if s}
    return [model.elements[i].id for i in model.sequence if model.elements[i].id in ids]


@pytest.mark.parametrize("k", [0, 1, 5, 9, 12])
def test_slider_shows_exactly_the_first_k_elements(live: LivePreview, model, k: int) -> None:
    live.gui.slider.value = k
    scene = live.scene
    assert scene.step == k
    seq_ids = [model.elements[i].id for i in model.sequence]
    assert visible_planned(model, scene) == [i for i in seq_ids[:k] if i.startswith("B")]
    prebuilt = [model.elements[i].id for i in np.flatnonzero(model.built_at == 0)]
    shown = np.any(scene.blocks.batched_scales > 0, axis=1)
    for i, s in zip(model.block_index, shown, strict=True):
        if model.elements[i].id in prebuilt:
            assert s
    ghost_shown = np.any(scene.ghost.batched_scales > 0, axis=1)
    assert np.array_equal(ghost_shown, ~shown)
    path = model.elements[model.path_index[0]]
    assert scene.paths[0].visible == (path.id in seq_ids[:k])
    tp = model.point_index[0]
    assert (scene.task_points.batched_scales[0] > 0) == (model.built_at[tp] <= k)


@pytest.mark.parametrize("k", [0, 3, 6, 7, 12])
def test_platform_and_arm_follow_the_step(live: LivePreview, model, k: int) -> None:
    live.gui.slider.value = k
    scene = live.scene
    p = 0 if k == 0 else int(model.step_package[k - 1])
    T = model.T_world_platform[p]
    np.testing.assert_allclose(scene.platform.position, T[:3, 3], atol=1e-6)
    yaw = 2 * np.arctan2(scene.platform.wxyz[3], scene.platform.wxyz[0])
    assert np.isclose(yaw, np.arctan2(T[1, 0], T[0, 0]), atol=1e-6)
    tip = scene.arm_joints.batched_positions[-1]
    if k == 0:
        T_world_flange = model.T_world_base[0] @ translation(*PointArm().home)
    else:
        T_world_flange = model.T_world_targets[k - 1] @ np.linalg.inv(T_FLANGE_TOOL)
        np.testing.assert_allclose(
            scene.tool.position, model.T_world_targets[k - 1][:3, 3], atol=1e-6
        )
    np.testing.assert_allclose(tip, T_world_flange[:3, 3], atol=1e-5)
    assert live.gui.station.value == model.station_at(k)
    assert f"Step {k} / {model.n_steps}" in live.gui.info.content


def test_station_dropdown_jumps_to_the_first_step_of_the_station(live: LivePreview, model) -> None:
    live.gui.slider.value = 0
    live.gui.station.value = "S2"
    first = int(np.flatnonzero(model.step_package == 1)[0]) + 1
    assert live.scene.step == first
    assert model.station_at(first) == "S2"
    assert model.station_at(first - 1) == "S1"


def test_colour_modes_change_colours_only(live: LivePreview, model) -> None:
    live.gui.slider.value = 7
    seen = {}
    for mode in COLOUR_MODES:
        before = (
            live.scene.blocks.batched_scales.copy(),
            live.scene.blocks.batched_positions.copy(),
            np.array(live.scene.platform.position),
        )
        with MessageLog(live.server) as log:
            live.gui.colour.value = mode
        assert log.scene_props() <= COLOUR_PROPS, log.scene_props()
        assert log.kinds() <= {"SceneNodeUpdateMessage", "GuiUpdateMessage"}, log.kinds()
        assert np.array_equal(before[0], live.scene.blocks.batched_scales)
        assert np.array_equal(before[1], live.scene.blocks.batched_positions)
        assert np.array_equal(before[2], live.scene.platform.position)
        seen[mode] = live.scene.blocks.batched_colors.copy()
        assert "rgb(" in live.gui.legend.content
    for a in COLOUR_MODES:
        for b in COLOUR_MODES:
            if a < b:
                assert not np.array_equal(seen[a], seen[b]), (a, b)
    live.gui.colour.value = "station"


def test_station_colours_follow_the_plan(model) -> None:
    colours = model.element_colours("station", 0)
    s1 = {
        tuple(colours[e]) for e, p in zip(model.sequence, model.step_package, strict=True) if p == 0
    }
    s2 = {
        tuple(colours[e]) for e, p in zip(model.sequence, model.step_package, strict=True) if p == 1
    }
    assert len(s1) == len(s2) == 1 and s1 != s2
    assert tuple(colours[np.flatnonzero(model.built_at == 0)[0]]) == (150, 150, 150)


def test_state_colours_mark_the_element_being_placed(model) -> None:
    c = model.element_colours("state", 5)
    placing = model.sequence[4]
    assert tuple(c[placing]) == (230, 60, 40)
    assert sum(tuple(row) == (230, 60, 40) for row in c) == 1


def test_deviation_colours_run_green_to_red(model) -> None:
    c = model.element_colours("deviation", 0).astype(int)
    dev = model.deviation
    low, high = int(np.nanargmin(dev)), int(np.nanargmax(dev))
    assert c[low, 1] > c[low, 0] and c[high, 0] > c[high, 1]
    unknown = int(np.flatnonzero(np.isnan(dev))[0])
    assert tuple(c[unknown]) == (200, 200, 200)


def test_steps_send_only_poses_visibility_and_colours(live: LivePreview, model) -> None:
    live.gui.colour.value = "state"
    with MessageLog(live.server) as log:
        for k in range(model.n_steps + 1):
            live.gui.slider.value = k
        for k in range(model.n_steps, -1, -3):
            live.gui.slider.value = k
    assert log.kinds() <= UPDATE_KINDS, log.kinds()
    assert log.scene_props() <= POSE_PROPS | VISIBILITY_PROPS | COLOUR_PROPS, log.scene_props()
    live.gui.colour.value = "station"


def test_deviation_without_simulation_is_an_input_error() -> None:
    elements, plan = wall_design()
    m = build_model(elements, plan)
    assert "deviation" not in m.colour_modes()
    with pytest.raises(InputError, match="--sim"):
        m.element_colours("deviation", 0)
    with pytest.raises(InputError, match="colour mode"):
        m.element_colours("rainbow", 0)
    with pytest.raises(InputError, match="step must be between"):
        m.visible(m.n_steps + 1)


def test_plan_that_names_unknown_elements_is_rejected() -> None:
    elements, plan = wall_design()
    wp = plan.work_packages[0]
    bad = Plan(
        work_packages=(
            WorkPackage(0, wp.station, ("nope",), np.eye(4)[None]),
            *plan.work_packages[1:],
        )
    )
    with pytest.raises(InputError, match="nope"):
        build_model(elements, bad)
    twice = Plan(work_packages=(wp, WorkPackage(1, wp.station, wp.elements, wp.T_world_targets)))
    with pytest.raises(InputError, match="more than once"):
        build_model(elements, twice)


def test_info_panel_shows_localization_residuals(model) -> None:
    elements, plan = wall_design()
    result = BasePose(
        T_world_base=model.T_world_base[0],
        covariance=np.diag([1e-6, 4e-6, 1e-6, 1e-6, 1e-6, 1e-6]),
        method="total_station",
        residuals=np.array([[0.001, 0.0, 0.0], [0.0, 0.002, 0.0]]),
        rmse=0.0016,
        station="S1",
    )
    m = build_model(elements, plan, localization={"S1": result})
    text = step_info(m, 1)
    assert "RMSE 1.6 mm" in text and "Residuals (mm): 1.0, 2.0" in text
    assert "σ xyz 1.0/2.0/1.0 mm" in text
    assert "no result loaded" in step_info(m, m.n_steps)


def test_program_download_has_targets_in_the_base_frame(model) -> None:
    name, content = work_package_json(model, 1)
    data = json.loads(content)
    assert name.endswith("_S2.json") and data["station"] == "S2"
    steps = np.flatnonzero(model.step_package == 1)
    expected = np.linalg.inv(model.T_world_base[1]) @ model.T_world_targets[steps]
    np.testing.assert_allclose(np.array(data["T_base_targets"]), expected, atol=1e-12)
    assert data["elements"] == [model.elements[i].id for i in model.sequence[steps]]


def test_program_download_never_holds_nan(model) -> None:
    lift = model.lift.copy()
    model.lift[1] = np.nan
    try:
        _, content = work_package_json(model, 1)
    finally:
        model.lift[:] = lift
    data = json.loads(content, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    assert data["lift"] is None


def test_unreachable_target_is_flagged() -> None:
    elements, plan = wall_design()
    m = build_model(elements, plan, arm=PointArm(reach=1.5))
    assert not m.arm_reached.all() and m.arm_reached[0]
    k = int(np.flatnonzero(~m.arm_reached)[0])
    np.testing.assert_allclose(m.arm_q[k], m.arm_q[k - 1])
    assert "not reachable" in step_info(m, k)


def test_kuka_arm_is_drawn_at_its_targets() -> None:
    robot = get_robot("kuka_kr60_3")
    rng = np.random.default_rng(3)
    station = Station("S1", translation(1.0, 2.0, 0.0, 0.4), lift=0.3)
    elements, packages = [], []
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    q = rng.uniform(lo * 0.5, hi * 0.5, size=(6, 6))
    T_wb = station.T_world_platform @ translation(0, 0, 0.3) @ translation(0, 0, 0.6)
    targets = T_wb @ robot.fk(q) @ T_FLANGE_TOOL
    for i, T in enumerate(targets):
        elements.append(
            Element(f"B{i}", "block", T, extents=np.array([0.6, 0.105, 0.105]), layer=i)
        )
    packages.append(WorkPackage(0, station, tuple(e.id for e in elements), targets))
    m = build_model(
        elements,
        Plan(work_packages=tuple(packages)),
        arm=RobotArm(robot, T_FLANGE_TOOL),
        T_flange_tool=T_FLANGE_TOOL,
    )
    assert m.arm_reached.all()
    np.testing.assert_allclose(m.arm_points[1:, -1], targets[:, :3, 3], atol=1e-6)
    np.testing.assert_allclose(m.arm_points[:, 0], np.broadcast_to(T_wb[:3, 3], (7, 3)), atol=1e-9)
    # every link keeps its length from step to step (a rigid arm)
    lengths = np.linalg.norm(np.diff(m.arm_points, axis=1), axis=2)
    np.testing.assert_allclose(lengths, np.broadcast_to(lengths[0], lengths.shape), atol=1e-9)


def test_localization_result_is_shown_at_its_visit_only() -> None:
    from fabflow.preview.export import quiet_server

    elements, plan = wall_design()
    T = translation(0.1, -1.5, 0.6)
    prisms = T[:3, 3] + np.array([[0.3, 0.0, 0.2], [-0.3, 0.0, 0.2], [0.0, 0.3, 0.25]])
    result = BasePose(
        T_world_base=T,
        covariance=np.eye(6) * 1e-6,
        method="total_station",
        rmse=0.001,
        station="S2",
        quality={"points_world": prisms.tolist()},
    )
    m = build_model(elements, plan, localization={1: result})
    with quiet_server() as server:
        scene = PreviewScene(server, m, step=0)
        ((key, frame),) = scene._results
        assert key == 1 and not frame.visible
        scene.set_step(m.first_step_of_station("S2"))
        assert frame.visible
        np.testing.assert_allclose(frame.position, T[:3, 3])
        cloud = server.scene._handle_from_node_name["/localization/results/visit_2/prisms"]
        np.testing.assert_allclose(cloud.points + T[:3, 3], prisms, atol=1e-2)
        scene.set_step(1)
        assert not frame.visible


def test_play_runs_to_the_end_and_pause_stops_it(live: LivePreview, model) -> None:
    import time

    gui = live.gui
    gui.speed.value = 60
    gui.slider.value = model.n_steps - 4
    gui.toggle_play()
    assert gui.playing and gui.play.label == "Pause"
    deadline = time.monotonic() + 10
    while gui.playing and time.monotonic() < deadline:
        time.sleep(0.02)
    gui.stop()
    assert live.scene.step == model.n_steps and gui.play.label == "Play"
    gui.speed.value = 1
    gui.toggle_play()  # at the end: starts again from step 0
    assert live.scene.step <= 1
    gui.toggle_play()
    gui.stop()
    assert not gui.playing
    assert live.scene.step <= 2


SITE_PROJECT = """\
name: site
site:
  extent_min: [-4.0, -4.0]
  extent_max: [6.0, 5.0]
  obstacles:
    - box: {name: store, min: [4.0, 3.0, 0.0], max: [5.0, 4.0, 2.0]}
    - polygon: {name: tree, points: [[-3, -3], [-2, -3], [-2.5, -2]], z_max: 4.0}
localization:
  method: icp
  icp: {map: map.xyz}
  uwb:
    anchors: {A1: [0, 0, 1], A2: [4, 0, 1], A3: [4, 4, 1]}
elements:
  - task_points:
      - {id: M1, pose: {xyz: [1, 0, 0]}}
"""


def test_site_obstacles_anchors_and_icp_map_are_drawn(tmp_path: Path) -> None:
    from fabflow.preview.export import quiet_server
    from fabflow.project import parse_project

    rng = np.random.default_rng(7)
    pts = rng.uniform(-3.0, 5.0, size=(500, 3))
    np.savetxt(tmp_path / "map.xyz", pts)
    project = parse_project(SITE_PROJECT, base_dir=tmp_path)
    elements, plan = wall_design()
    m = build_model(elements, plan)
    with quiet_server() as server:
        PreviewScene(server, m, project)
        nodes = server.scene._handle_from_node_name
        assert "/site/obstacles/0_store" in nodes and "/site/obstacles/1_tree" in nodes
        np.testing.assert_allclose(nodes["/site/obstacles/0_store"].position, (4.5, 3.5, 1.0))
        np.testing.assert_allclose(nodes["/localization/icp_map"].points, pts, atol=1e-5)
        anchors = nodes["/localization/uwb_anchors"].batched_positions
        np.testing.assert_allclose(anchors, [[0, 0, 1], [4, 0, 1], [4, 4, 1]])
        assert "/localization/total_station" not in nodes
        grid = nodes["/site/grid"]
        assert (grid.width, grid.height) == (10.0, 9.0)


def test_legend_text_names_every_colour(model) -> None:
    assert "S1 blue" in model.legend_text("station") and "S2 orange" in model.legend_text("station")
    assert "red being placed" in model.legend_text("state")
    assert "10 mm (tolerance)" in model.legend_text("deviation")
    with pytest.raises(InputError):
        model.legend_text("rainbow")


def test_prism_of_a_concave_outline_has_the_right_volume() -> None:
    import trimesh

    from fabflow.preview.scene import _prism

    outline = np.array([[0, 0], [3, 0], [3, 1], [1, 1], [1, 2], [0, 2]], dtype=float)
    vertices, faces = _prism(outline, 2.0)
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    mesh.merge_vertices()
    mesh.fix_normals()
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(4.0 * 2.0)


@settings(deadline=None, max_examples=60)
@given(
    st.lists(
        st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 3).filter(
            lambda v: np.linalg.norm(v) > 1e-3
        ),
        min_size=1,
        max_size=8,
    )
)
def test_link_quaternion_turns_z_onto_the_link(directions) -> None:
    from fabflow.preview.scene import _quat_z_to
    from fabflow.transforms.so3 import matrix_from_quat

    d = np.array(directions, dtype=float)
    d = np.vstack([d, [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    R = matrix_from_quat(_quat_z_to(d))
    np.testing.assert_allclose(R[:, :, 2], d, atol=1e-6)  # display precision


def test_layer_colours_span_the_layers_present() -> None:
    elements, plan = wall_design()
    shifted = [dataclasses.replace(e, layer=e.layer + 5) for e in elements]
    c = build_model(shifted, plan).element_colours("layer", 0).astype(int)
    layers = np.array([e.layer for e in shifted])
    lowest, highest = np.argmin(layers), np.argmax(layers)
    assert tuple(c[lowest]) == (68, 1, 84)  # viridis at 0
    assert tuple(c[highest]) == (253, 231, 37)  # viridis at 1
