"""``fabflow export``: real build folders to Rhino .3dm and COMPAS JSON, read back directly."""

from __future__ import annotations

import csv
import json
import shutil
from collections import Counter
from pathlib import Path

import compas
import numpy as np
import pytest
import rhino3dm
from compas.geometry import Transformation
from helpers import DATA
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from fabflow.cli import app
from fabflow.design import exchange
from fabflow.design.export_data import frame_from_text
from fabflow.design.supports import box_corners

TINY_CABIN = """\
name: tiny-cabin
site: {extent_min: [-3.0, -3.0], extent_max: [5.0, 5.0]}
robot:
  model: kuka_kr60_3
  tool: {name: gripper, T_flange_tool: {xyz: [0.0, 0.0, 0.25]}, mass: 18.0, cog: [0.0, 0.0, 0.11]}
  platform:
    footprint: [1.6, 1.2]
    lift: [0.0, 0.6]
    T_platform_base: {xyz: [0.6, 0.0, 0.3], abc_deg: [180, 0, 0]}
    T_platform_pick: {xyz: [-0.3, 0.0, 0.9]}
    safety_margin: 0.15
localization:
  method: total_station
  total_station: {instrument: leica_ms50, T_world_instrument: {xyz: [-2.0, -2.0, 1.6]}, n_points: 4}
elements:
  - cabin: {length: 1.8, width: 1.5, height: 0.45, eave_height: 0.35, openings: []}
tolerances: {position: 0.05, rotation_deg: 2.0}
program: {format: krl}
"""
"""42 blocks in parts A, B, C (robot) and front, rear (by hand) from 2 stations, localized
by a total station: builds in a few seconds."""


@pytest.fixture(scope="module")
def builds(tmp_path_factory):
    """A tiny cabin (total station) built and simulated once; the small UWB project built."""
    root = tmp_path_factory.mktemp("export")
    (root / "tiny").mkdir()
    (root / "tiny" / "project.yaml").write_text(TINY_CABIN)
    runner = CliRunner()
    simulate = ["simulate", str(root / "tiny"), "-n", "1", "--workers", "0", "--no-plots"]
    for args in (
        ["build", str(root / "tiny"), "-o", str(root / "cabin")],
        [*simulate, "-o", str(root / "sim")],
        ["build", str(DATA / "sim" / "project.yaml"), "-o", str(root / "uwb")],
    ):
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
    return root


def load(folder: Path, name: str):
    return json.loads((folder / name).read_text())


def expected_layout(folder: Path):
    """Element by id, station of each planned element, footprints by station (4 corners)."""
    elements = {e["id"]: e for e in load(folder, "elements.json")["elements"]}
    plan = load(folder, "plan.json")
    length, width = load(folder, "project.json")["project"]["robot"]["platform"]["footprint"]
    station_of, footprints = {}, {}
    local = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * [length / 2, width / 2]
    for wp in plan["work_packages"]:
        sid = wp["station"]["id"]
        station_of.update({eid: sid for eid in wp["elements"]})
        T = np.array(wp["station"]["T_world_platform"])
        homogeneous = np.column_stack([local, np.zeros(4), np.ones(4)])
        footprints[sid] = (homogeneous @ T.T)[:, :3]
    return elements, station_of, footprints


def asbuilt_poses(path: Path) -> dict[str, np.ndarray]:
    """The as-built table read independently: KUKA A, B, C are intrinsic z, y', x''."""
    out = {}
    with path.open() as f:
        for row in csv.DictReader(f):
            T = np.eye(4)
            abc = [float(row[f"asbuilt_{c}_deg"]) for c in "abc"]
            T[:3, :3] = Rotation.from_euler("ZYX", abc, degrees=True).as_matrix()
            T[:3, 3] = [float(row[f"asbuilt_{c}_m"]) for c in "xyz"]
            out[row["element"]] = T
    return out


def same_points(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    d = np.linalg.norm(np.asarray(a)[:, None] - np.asarray(b)[None], axis=2)
    return len(a) == len(b) and d.min(axis=1).max() < tol and d.min(axis=0).max() < tol


def test_export_3dm_of_a_build(cli, builds, tmp_path) -> None:
    target = tmp_path / "site" / "plan.3dm"
    result = cli(
        "export", str(builds / "cabin"), "--to", str(target), "--asbuilt", str(builds / "sim")
    )
    assert result.returncode == 0, result.stderr
    assert "wrote" in result.stdout and "42 elements (13 unplanned), 2 stations" in result.stdout
    assert [p.name for p in target.parent.iterdir()] == ["plan.3dm"]
    model = rhino3dm.File3dm.Read(str(target))
    assert model.Settings.ModelUnitSystem == rhino3dm.UnitSystem.Meters
    layers = [layer.FullPath for layer in model.Layers]
    elements, station_of, footprints = expected_layout(builds / "cabin")

    def on(path: str) -> list:
        return [o for o in model.Objects if layers[o.Attributes.LayerIndex] == path]

    expected = Counter(
        f"fabflow::elements::{station_of.get(eid, 'unplanned')}::{e['part'] or 'no_part'}"
        for eid, e in elements.items()
    )
    assert expected["fabflow::elements::unplanned::front"] and len(expected) >= 5
    got = Counter(
        layers[o.Attributes.LayerIndex]
        for o in model.Objects
        if layers[o.Attributes.LayerIndex].startswith("fabflow::elements::")
    )
    assert got == expected
    for layer, n in expected.items():
        objects = on(layer)
        assert len(objects) == n
        for o in objects:
            e = elements[o.Attributes.Name]
            T = frame_from_text(o.Attributes.GetUserString(exchange.KEY_FRAME))
            assert T.tolist() == e["T_world_element"]  # every float exactly
            assert o.Attributes.GetUserString(exchange.KEY_ID) == e["id"]
            corners = box_corners(T[None], np.array([e["extents"]]))[0]
            assert isinstance(o.Geometry, rhino3dm.Extrusion)
            brep = o.Geometry.ToBrep(True)
            pts = [[v.Location.X, v.Location.Y, v.Location.Z] for v in brep.Vertices]
            assert same_points(pts, corners, 1e-9)
    outlines = [o for o in on("fabflow::stations") if o.Geometry.ObjectType.name == "Curve"]
    assert {o.Attributes.Name for o in outlines} == set(footprints) == {"S1", "S2"}
    for o in outlines:
        c = o.Geometry
        pts = np.array([[c.Point(i).X, c.Point(i).Y, c.Point(i).Z] for i in range(c.PointCount)])
        assert c.IsClosed and len(pts) == 5 and np.array_equal(pts[0], pts[-1])
        assert same_points(pts[:4], footprints[o.Attributes.Name], 1e-12)
    dots = [
        o.Geometry.Text for o in on("fabflow::stations") if o.Geometry.ObjectType.name != "Curve"
    ]
    assert sorted(dots) == ["S1", "S2"]
    setups = load(builds / "cabin", "instrument_setups.json")["setups"]
    got_setups = {
        o.Attributes.Name: [o.Geometry.Location.X, o.Geometry.Location.Y, o.Geometry.Location.Z]
        for o in on("fabflow::setups")
    }
    assert got_setups == {s["id"]: s["position"] for s in setups}
    asbuilt = asbuilt_poses(builds / "sim" / "asbuilt_run0.csv")
    built = on("fabflow::as_built")
    assert sorted(o.Attributes.Name for o in built) == sorted(asbuilt) and len(asbuilt) == 29
    for o in built:
        T = frame_from_text(o.Attributes.GetUserString(exchange.KEY_FRAME))
        assert np.abs(T - asbuilt[o.Attributes.Name]).max() < 1e-9


def test_export_compas_json_of_a_build(cli, builds, tmp_path) -> None:
    target = tmp_path / "plan.json"
    args = ["export", str(builds / "cabin"), "-o", str(target), "--asbuilt", str(builds / "sim")]
    assert cli(*args).returncode == 0
    doc = compas.json_load(str(target))
    elements, station_of, footprints = expected_layout(builds / "cabin")
    assert doc["fabflow"] == 1 and doc["units"] == "m" and len(doc["elements"]) == 42
    for r in doc["elements"]:
        e = elements[r["id"]]
        M = np.array(Transformation.from_frame(r["frame"]).matrix)
        assert np.abs(M - e["T_world_element"]).max() < 1e-9
        assert r["station"] == station_of.get(r["id"]) and r["part"] == e["part"]
        assert r["supports"] == e["supports"] and r["robot_built"] == e["robot_built"]
        corners = box_corners(np.array([e["T_world_element"]]), np.array([e["extents"]]))[0]
        assert same_points(r["geometry"].points, corners, 1e-9)
    plan = load(builds / "cabin", "plan.json")
    for s in doc["stations"]:
        planned = [wp for wp in plan["work_packages"] if wp["station"]["id"] == s["id"]]
        assert s["elements"] == [eid for wp in planned for eid in wp["elements"]]
        pts = np.array(s["footprint"].points)
        assert np.array_equal(pts[0], pts[-1]) and same_points(pts[:4], footprints[s["id"]], 1e-12)
    asbuilt = asbuilt_poses(builds / "sim" / "asbuilt_run0.csv")
    got = {a["id"]: np.array(Transformation.from_frame(a["frame"]).matrix) for a in doc["as_built"]}
    assert set(got) == set(asbuilt)
    assert max(np.abs(got[k] - asbuilt[k]).max() for k in got) < 1e-9


def test_export_of_a_uwb_build_has_its_anchors_and_task_points(builds, tmp_path) -> None:
    target = tmp_path / "uwb.3dm"
    result = CliRunner().invoke(app, ["export", str(builds / "uwb"), "--to", str(target)])
    assert result.exit_code == 0, result.output
    model = rhino3dm.File3dm.Read(str(target))
    layers = [layer.FullPath for layer in model.Layers]
    anchors = load(builds / "uwb", "uwb_anchors.json")["anchors"]
    got = {
        o.Attributes.Name: [o.Geometry.Location.X, o.Geometry.Location.Y, o.Geometry.Location.Z]
        for o in model.Objects
        if layers[o.Attributes.LayerIndex] == "fabflow::anchors"
    }
    assert got == anchors
    points = [
        o
        for o in model.Objects
        if layers[o.Attributes.LayerIndex] == "fabflow::elements::S1::no_part"
    ]
    assert sorted(o.Attributes.Name for o in points) == ["P1", "P2", "P3", "P4"]
    assert all(isinstance(o.Geometry, rhino3dm.Point) for o in points)


def test_export_replaces_an_existing_file_in_one_step(builds, tmp_path) -> None:
    target = tmp_path / "plan.json"
    target.write_text("an earlier export")
    result = CliRunner().invoke(app, ["export", str(builds / "uwb"), "-o", str(target)])
    assert result.exit_code == 0, result.output
    assert compas.json_load(str(target))["fabflow"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["plan.json"]


def broken_copy(builds: Path, tmp_path: Path, name: str, text: str) -> Path:
    folder = tmp_path / "broken"
    shutil.copytree(builds / "cabin", folder)
    (folder / name).write_text(text)
    return folder


def nan_pose(builds: Path) -> str:
    data = load(builds / "cabin", "elements.json")
    data["elements"][5]["T_world_element"][0][3] = None
    return json.dumps(data)


BAD_INPUTS = {
    "missing folder": (lambda b, t: [str(t / "nowhere")], "build output folder does not exist"),
    "no elements.json": (lambda b, t: [str(t)], "has no elements.json"),
    "corrupt plan.json": (
        lambda b, t: [str(broken_copy(b, t, "plan.json", '{"work_packages": ['))],
        "plan.json: line 1: plan file is not valid JSON",
    ),
    "not a plan": (
        lambda b, t: [str(broken_copy(b, t, "plan.json", '{"work_packages": [{"index": 0}]}'))],
        "not a fabflow plan: missing field 'station'",
    ),
    "NaN in elements.json": (
        lambda b, t: [str(broken_copy(b, t, "elements.json", '{"elements": [NaN]}'))],
        "NaN is not a number",
    ),
    "null in a pose": (
        lambda b, t: [str(broken_copy(b, t, "elements.json", nan_pose(b)))],
        "elements[5] (B0005): T_world_element must be 4x4 finite numbers",
    ),
    "as-built of another design": (
        lambda b, t: [str(b / "uwb"), "--asbuilt", str(b / "sim")],
        "is not in the build: the simulation was run on another design",
    ),
    "no as-built table": (
        lambda b, t: [str(b / "cabin"), "--asbuilt", str(b / "cabin")],
        "has no asbuilt_run0.csv",
    ),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_exits_2_with_one_message(builds, tmp_path, case) -> None:
    args, message = BAD_INPUTS[case]
    target = tmp_path / "out" / "plan.3dm"
    result = CliRunner().invoke(app, ["export", *args(builds, tmp_path), "-o", str(target)])
    assert result.exit_code == 2, result.output
    assert "error:" in result.output and message in " ".join(result.output.split())
    assert "Traceback" not in result.output and not target.exists()


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("plan.txt", "unknown export format '.txt': expected .3dm (Rhino) or .json (COMPAS"),
        ("plan", "unknown export format '(no suffix)'"),
        ("elements.json", "is one of the export's inputs"),
    ],
)
def test_bad_target_exits_2_without_traceback(cli, builds, name, message) -> None:
    target = builds / "cabin" / name
    before = target.read_bytes() if target.exists() else None
    result = cli("export", str(builds / "cabin"), "-o", str(target))
    assert result.returncode == 2 and message in " ".join(result.stderr.split())
    assert "Traceback" not in result.stdout + result.stderr
    assert (target.read_bytes() if target.exists() else None) == before
