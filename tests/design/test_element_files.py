"""Elements from files: elements.json, COMPAS JSON and Rhino .3dm, box frames, bad files."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import compas
import jsonschema
import numpy as np
import pytest
import rhino3dm
from compas.datastructures import Mesh
from compas.geometry import Box, Frame, Polyline
from helpers import PROJECTS
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fabflow.design import exchange
from fabflow.design.box_pose import box_pose_from_corners, oriented_box_pose
from fabflow.design.element_files import file_elements
from fabflow.design.element_records import elements_file_schema
from fabflow.design.elements import elements_to_json
from fabflow.design.generate import generate_elements
from fabflow.design.specs import ElementFileSpec
from fabflow.errors import InputError
from fabflow.project import parse_project

WALL = PROJECTS / "timber_wall"
SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) / 2.0


def _corners(T: np.ndarray, extents: np.ndarray) -> np.ndarray:
    """(8, 3) world corners of the box of pose T and size extents."""
    return (SIGNS * extents) @ T[:3, :3].T + T[:3, 3]


def _pose(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = t
    return T


def _read(path: Path, **kw):
    return file_elements(ElementFileSpec(path=path, **kw), 0, 10_000)


def _write_3dm(path: Path, boxes, units=rhino3dm.UnitSystem.Meters, scale=1.0, layer="blocks"):
    """A .3dm of boxes (pose, extents) as a user draws them: breps, no user text."""
    model = rhino3dm.File3dm()
    model.Settings.ModelUnitSystem = units
    lay = rhino3dm.Layer()
    lay.Name = layer
    index = model.Layers.Add(lay)
    for i, (T, ext) in enumerate(boxes):
        half = np.asarray(ext) / 2.0 * scale
        brep = rhino3dm.Brep.CreateFromBox(rhino3dm.Box(rhino3dm.BoundingBox(*(-half), *half)))
        M = rhino3dm.Transform(1.0)
        for r in range(4):
            for c in range(4):
                v = T[r, c] * (scale if c == 3 and r < 3 else 1.0)
                setattr(M, f"M{r}{c}", float(v))
        brep.Transform(M)
        attributes = rhino3dm.ObjectAttributes()
        attributes.LayerIndex = index
        attributes.Name = f"X{i:03d}"
        model.Objects.AddBrep(brep, attributes)
    assert model.Write(str(path), 8)


# ----------------------------------------------------------------------- box frames


rigid = st.tuples(
    st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
    st.lists(st.floats(-50, 50), min_size=3, max_size=3),
    st.lists(st.floats(0.01, 3.0), min_size=3, max_size=3),
)


@settings(max_examples=60, deadline=None)
@given(rigid, st.permutations(range(8)))
def test_box_pose_from_corners_gives_the_same_box(box, order) -> None:
    q, t, ext = (np.asarray(v, dtype=float) for v in box)
    T = _pose(q, t)
    corners = _corners(T, ext)[list(order)]
    T_found, ext_found = box_pose_from_corners(corners[None])
    # the same set of corners, in a right-handed frame with z up-ish
    found = _corners(T_found[0], ext_found[0])
    dist = np.linalg.norm(found[:, None, :] - corners[None, :, :], axis=2).min(axis=1)
    assert dist.max() < 1e-9
    assert np.linalg.det(T_found[0][:3, :3]) == pytest.approx(1.0, abs=1e-9)
    assert T_found[0][2, 2] >= 0.0
    assert np.sort(ext_found[0]) == pytest.approx(np.sort(ext), abs=1e-9)


@settings(max_examples=40, deadline=None)
@given(rigid, st.sampled_from([(0, 1, 2), (1, 2, 0), (2, 0, 1)]), st.sampled_from([1, -1]))
# a cube turned so that two of its axes are equally vertical: ties all the way down
@example(([0.0, 0.5, 0.25, 0.25], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]), (0, 1, 2), -1)
@example(([0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]), (1, 2, 0), 1)
@example(([0.0, 0.0, 0.38268343, 0.92387953], [1.0, 2.0, 0.0], [1.0, 1.0, 0.5]), (2, 0, 1), -1)
def test_box_frame_does_not_depend_on_how_the_box_was_drawn(box, perm, sign) -> None:
    """Another frame of the same box (axes permuted and flipped) gives the same pose."""
    q, t, ext = (np.asarray(v, dtype=float) for v in box)
    T = _pose(q, t)
    other = T.copy()
    other[:3, :3] = T[:3, list(perm)] * np.array([sign, sign, 1.0])
    T1, _ = box_pose_from_corners(_corners(T, ext)[None])
    T2, _ = box_pose_from_corners(_corners(other, ext[list(perm)])[None])
    assert np.abs(T1 - T2).max() < 1e-9


def test_a_block_lying_along_y_gets_x_along_its_length() -> None:
    T = np.eye(4)
    T[:3, 3] = (1.0, 2.0, 0.3)
    corners = _corners(T, np.array([0.105, 0.6, 0.105]))
    T_found, ext = box_pose_from_corners(corners[None])
    assert ext[0] == pytest.approx([0.6, 0.105, 0.105])
    assert T_found[0][:3, 0] == pytest.approx([0.0, 1.0, 0.0])
    assert T_found[0][:3, 2] == pytest.approx([0.0, 0.0, 1.0])


def test_corners_that_are_no_box_are_refused() -> None:
    corners = _corners(np.eye(4), np.array([1.0, 0.5, 0.2]))
    corners[3] += (0.0, 0.0, 0.01)
    with pytest.raises(ValueError, match="box 0"):
        box_pose_from_corners(corners[None])


def test_oriented_box_of_a_mesh() -> None:
    T = _pose(np.array([0.1, 0.2, 0.3, 0.9]), np.array([1.0, -2.0, 0.5]))
    T_found, ext = oriented_box_pose(_corners(T, np.array([0.6, 0.2, 0.1])))
    assert np.sort(ext) == pytest.approx([0.1, 0.2, 0.6], abs=1e-6)
    assert T_found[:3, 3] == pytest.approx(T[:3, 3], abs=1e-9)
    with pytest.raises(ValueError, match="flat"):
        oriented_box_pose(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]))


# ------------------------------------------------------------------ the three formats


def test_the_wall_from_compas_and_from_3dm_is_the_same(tmp_path) -> None:
    """The example's 50 COMPAS Boxes and the same boxes drawn in Rhino give one design."""
    from_compas, given_c = _read(WALL / "wall.json")
    boxes = [(e.T_world_element, e.extents) for e in from_compas]
    _write_3dm(tmp_path / "wall.3dm", boxes)
    from_rhino, given_r = _read(tmp_path / "wall.3dm")
    assert len(from_compas) == len(from_rhino) == 50
    assert not given_c and not given_r  # supports computed from the geometry
    for a, b in zip(from_compas, from_rhino, strict=True):
        assert np.abs(a.T_world_element - b.T_world_element).max() < 1e-9
        assert np.abs(a.extents - b.extents).max() < 1e-9
        assert a.layer == b.layer
    assert [e.layer for e in from_compas] == [k // 5 for k in range(50)]


def test_a_millimetre_3dm_is_scaled_to_metres(tmp_path) -> None:
    from_compas, _ = _read(WALL / "wall.json")
    boxes = [(e.T_world_element, e.extents) for e in from_compas[:5]]
    _write_3dm(tmp_path / "mm.3dm", boxes, rhino3dm.UnitSystem.Millimeters, 1000.0)
    from_mm, _ = _read(tmp_path / "mm.3dm")
    for a, b in zip(from_compas, from_mm, strict=False):
        assert np.abs(a.T_world_element - b.T_world_element).max() < 1e-9
        assert np.abs(a.extents - b.extents).max() < 1e-9


def test_layers_and_user_text_of_a_3dm(tmp_path) -> None:
    """Type from the layer, id, part, supports and frame from user text; layer filter."""
    model = rhino3dm.File3dm()
    model.Settings.ModelUnitSystem = rhino3dm.UnitSystem.Meters
    for name in ("walls", "task_points", "notes"):
        lay = rhino3dm.Layer()
        lay.Name = name
        model.Layers.Add(lay)
    a = rhino3dm.ObjectAttributes()
    a.LayerIndex = 0
    a.SetUserString(exchange.KEY_ID, "low")
    brep = rhino3dm.Brep.CreateFromBox(rhino3dm.Box(rhino3dm.BoundingBox(0, 0, 0, 0.6, 0.1, 0.1)))
    model.Objects.AddBrep(brep, a)
    b = rhino3dm.ObjectAttributes()
    b.LayerIndex = 0
    b.SetUserString(exchange.KEY_ID, "high")
    b.SetUserString(exchange.KEY_PART, "north")
    b.SetUserString(exchange.KEY_SUPPORTS, "low")
    T = np.eye(4)
    T[:3, 3] = (0.3, 0.05, 0.15)
    T[:3, :3] = [[-1, 0, 0], [0, -1, 0], [0, 0, 1]]
    b.SetUserString(exchange.KEY_FRAME, json.dumps(T.ravel().tolist()))
    brep2 = rhino3dm.Brep.CreateFromBox(
        rhino3dm.Box(rhino3dm.BoundingBox(0, 0, 0.1, 0.6, 0.1, 0.2))
    )
    model.Objects.AddBrep(brep2, b)
    c = rhino3dm.ObjectAttributes()
    c.LayerIndex = 1
    c.SetUserString(exchange.KEY_ID, "drill1")
    Tc = np.eye(4)
    Tc[:3, :3] = np.diag([1.0, -1.0, -1.0])
    Tc[:3, 3] = (1.0, 1.0, 0.5)
    c.SetUserString(exchange.KEY_FRAME, json.dumps(Tc.ravel().tolist()))
    model.Objects.AddPoint(rhino3dm.Point3d(1.0, 1.0, 0.5), c)
    d = rhino3dm.ObjectAttributes()
    d.LayerIndex = 2
    model.Objects.AddCurve(
        rhino3dm.LineCurve(rhino3dm.Point3d(0, 0, 0), rhino3dm.Point3d(1, 0, 0)), d
    )
    path = tmp_path / "mixed.3dm"
    assert model.Write(str(path), 8)
    with pytest.raises(InputError, match="LineCurve is not an element"):
        _read(path)
    elements, given = _read(path, layers=["walls", "task_points"])
    by_id = {e.id: e for e in elements}
    assert given  # one object names its supports: the file's are used
    assert by_id["high"].supports == ("low",) and by_id["low"].supports == ()
    assert by_id["high"].part == "north"
    assert np.array_equal(by_id["high"].T_world_element, T)
    assert by_id["high"].extents == pytest.approx([0.6, 0.1, 0.1])
    assert by_id["low"].layer == 0 and by_id["high"].layer == 1
    assert by_id["drill1"].type == "task_point"
    assert np.array_equal(by_id["drill1"].T_world_element, Tc)


def test_compas_boxes_meshes_frames_and_records(tmp_path) -> None:
    T = np.eye(4)
    T[:3, 3] = (1.0, 2.0, 0.05)
    mesh = Mesh.from_vertices_and_faces(_corners(T, np.array([0.6, 0.1, 0.1])).tolist(), [])
    frame = Frame([0.0, 0.0, 1.0], [1, 0, 0], [0, -1, 0])
    box = Box(0.1, 0.6, 0.1, frame=Frame([3.0, 0.0, 0.05], [1, 0, 0], [0, 1, 0]))
    kept = Frame([5.0, 0.0, 0.05], [0, 1, 0], [-1, 0, 0])
    doc = {
        "elements": [
            mesh,
            frame,
            box,
            {
                "id": "R1",
                "frame": kept,
                "geometry": Box(0.6, 0.1, 0.1, frame=kept),
                "part": "P",
                "layer": 3,
            },
        ]
    }
    path = tmp_path / "mixed.json"
    compas.json_dump(doc, str(path))
    elements, given = _read(path)
    assert [e.type for e in elements] == ["block", "task_point", "block", "block"]
    assert [e.id for e in elements][:3] == ["mixed-0000", "mixed-0001", "mixed-0002"]
    assert elements[0].extents == pytest.approx([0.6, 0.1, 0.1], abs=1e-6)
    assert elements[1].T_world_element[:3, 2] == pytest.approx([0, 0, -1])
    # a bare box gets x along its length (world y here); a record keeps its frame
    assert elements[2].extents == pytest.approx([0.6, 0.1, 0.1])
    assert elements[2].T_world_element[:3, 0] == pytest.approx([0, 1, 0])
    assert elements[3].T_world_element[:3, 0] == pytest.approx([0, 1, 0])
    assert elements[3].part == "P" and elements[3].layer == 3
    assert not given


def test_elements_json_of_a_build_reads_back_exactly(tmp_path) -> None:
    project = parse_project("name: t\nelements:\n  - cabin: {}\n")
    elements = generate_elements(project.elements)
    doc = {"frame": "world", "units": "m", "count": len(elements)}
    doc["elements"] = elements_to_json(elements)
    jsonschema.validate(doc, elements_file_schema())
    (tmp_path / "elements.json").write_text(json.dumps(doc))
    back, given = _read(tmp_path / "elements.json")
    assert given
    for a, b in zip(elements, back, strict=True):
        assert a.id == b.id and a.layer == b.layer and a.part == b.part
        assert a.supports == b.supports and a.robot_built == b.robot_built
        assert np.array_equal(a.T_world_element, b.T_world_element)
        assert np.array_equal(a.extents, b.extents)


# ------------------------------------------------------------------- in a project


def test_a_project_plans_its_file_elements_with_a_cabin(tmp_path) -> None:
    shutil.copy(WALL / "wall.json", tmp_path / "wall.json")
    text = (
        "name: t\nelements:\n  - cabin: {origin: [10, 10, 0]}\n"
        "  - file: {path: wall.json, part: wall}\n"
    )
    (tmp_path / "project.yaml").write_text(text)
    project = parse_project(text, source=tmp_path / "project.yaml", base_dir=tmp_path)
    elements = generate_elements(project.elements, project.path, project.limits)
    wall = [e for e in elements if e.part == "wall"]
    assert len(wall) == 50 and wall[0].id == "W000"
    # supports computed across all blocks: W005 (course 1) rests on W000 and W001
    assert set(next(e for e in wall if e.id == "W005").supports) == {"W000", "W001"}
    assert all(e.attributes["source_index"] == 1 for e in wall)


def test_an_id_used_by_the_cabin_and_a_file_is_refused(tmp_path) -> None:
    T = np.eye(4)
    T[:3, 3] = (20.0, 0.0, 0.05)
    doc = {"elements": [{"id": "B0000", "T_world_element": T.tolist(), "extents": [0.6, 0.1, 0.1]}]}
    doc["frame"] = "world"
    (tmp_path / "e.json").write_text(json.dumps(doc))
    text = "name: t\nelements:\n  - cabin: {}\n  - file: e.json\n"
    project = parse_project(text, source=tmp_path / "p.yaml", base_dir=tmp_path)
    with pytest.raises(InputError, match=r"'B0000' is used twice") as info:
        generate_elements(project.elements, project.path, project.limits)
    assert "elements[1].file" in str(info.value)


# ------------------------------------------------------------------------- bad files


def _block(i: int = 0, **kw) -> dict:
    T = np.eye(4)
    T[0, 3] = i
    return {"id": f"E{i}", "T_world_element": T.tolist(), "extents": [0.6, 0.1, 0.1], **kw}


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("not json", "not a JSON file"),
        ('{"frame": "world", "elements": [{"id": "a", "T_world_element": NaN}]}', "NaN"),
        ('{"frame": "world", "elements": []}', "no elements"),
        (json.dumps({"frame": "world", "elements": [_block(), _block()]}), "used twice"),
        (json.dumps({"frame": "world", "elements": [_block(supports=["Z"])]}), "not in the file"),
        (json.dumps({"frame": "world", "elements": [_block(type="print_path")]}), "print_path"),
        (json.dumps({"frame": "world", "elements": [_block(id="a b")]}), "pattern"),
        (json.dumps({"frame": "world", "count": 3, "elements": [_block()]}), "'count' is 3"),
        (
            json.dumps({"frame": "world", "elements": [{"id": "a", "T_world_element": 4}]}),
            "T_world_element",
        ),
        (
            json.dumps(
                {
                    "frame": "world",
                    "elements": [
                        {**_block(), "T_world_element": np.diag([2.0, 1, 1, 1]).tolist()},
                    ],
                }
            ),
            "not a rotation matrix",
        ),
        (
            json.dumps({"frame": "world", "elements": [{**_block(), "extents": None}]}),
            "needs 'extents'",
        ),
        (json.dumps([{"dtype": "os/system", "data": {}}]), "is not read here"),
        (json.dumps([{"dtype": "compas.geometry/Box", "data": {}}]), "not COMPAS data"),
        (
            json.dumps({"elements": [Polyline([[0, 0, 0], [1, 0, 0]]).__jsondump__()]}),
            "Polyline is not an element",
        ),
        ("[" * 100_000 + "]" * 100_000, "not a JSON file"),
    ],
)
def test_bad_json_files_are_one_clear_error(tmp_path, text, match) -> None:
    path = tmp_path / "e.json"
    path.write_text(text)
    with pytest.raises(InputError, match=match) as info:
        _read(path)
    assert str(path) in str(info.value)


def test_too_many_elements_are_refused_before_they_are_made(tmp_path) -> None:
    path = tmp_path / "e.json"
    path.write_text(json.dumps({"frame": "world", "elements": [_block(i) for i in range(5)]}))
    with pytest.raises(InputError, match=r"more than limits\.max_elements"):
        file_elements(ElementFileSpec(path=path), 0, 4)


def test_bad_3dm_files_are_one_clear_error(tmp_path) -> None:
    path = tmp_path / "e.3dm"
    path.write_bytes(b"\x00not a rhino file" * 10)
    with pytest.raises(InputError, match=r"not a Rhino \.3dm file"):
        _read(path)
    _write_3dm(path, [(np.eye(4), [0.6, 0.1, 0.1])], units=rhino3dm.UnitSystem.Unset)
    with pytest.raises(InputError, match="set 'units'"):
        _read(path)
    assert len(_read(path, units="mm")[0]) == 1
    model = rhino3dm.File3dm()
    model.Settings.ModelUnitSystem = rhino3dm.UnitSystem.Meters
    model.Objects.AddPoint(rhino3dm.Point3d(0, 0, 0))
    model.Write(str(path), 8)
    with pytest.raises(InputError, match=r"a point needs a 'fabflow\.frame'"):
        _read(path)


@settings(max_examples=150, deadline=None)
@given(
    st.recursive(
        st.none() | st.booleans() | st.floats(allow_nan=False) | st.text(max_size=8),
        lambda inner: (
            st.lists(inner, max_size=4)
            | st.dictionaries(
                st.sampled_from(
                    "id type T_world_element extents supports layer elements frame count part "
                    "attributes dtype data geometry".split()
                ),
                inner,
                max_size=5,
            )
        ),
        max_leaves=20,
    )
)
def test_any_json_is_read_or_refused_with_a_message(tmp_path_factory, doc) -> None:
    path = tmp_path_factory.mktemp("fuzz") / "e.json"
    path.write_text(json.dumps(doc))
    try:
        elements, _ = _read(path)
    except InputError as exc:
        assert str(path) in str(exc)
    else:
        assert all(np.isfinite(e.T_world_element).all() for e in elements)
