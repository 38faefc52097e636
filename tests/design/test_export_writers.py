"""The Rhino .3dm and COMPAS JSON writers: read back with rhino3dm and compas directly."""

from __future__ import annotations

import json
import math
import sys
from collections import Counter
from pathlib import Path

import compas
import numpy as np
import pytest
import rhino3dm
from compas.geometry import Transformation
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.design import exchange
from fabflow.design.compas_out import compas_document, compas_frame, write_compas_json
from fabflow.design.elements import Element
from fabflow.design.export_data import (
    StationRecord,
    element_user_text,
    export_content,
    frame_from_text,
    frame_text,
    platform_footprints,
    world_polyline,
)
from fabflow.design.rhino_out import layer_name, write_3dm
from fabflow.design.supports import box_corners
from fabflow.errors import InputError, UnsupportedError
from fabflow.transforms.so3 import matrix_from_quat

unit = st.floats(-1.0, 1.0, allow_nan=False)
quats = st.tuples(unit, unit, unit, unit).filter(lambda q: np.linalg.norm(q) > 0.1)
coord = st.floats(-500.0, 500.0, allow_nan=False)


def rigid(q, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(np.asarray(q) / np.linalg.norm(q))
    T[:3, 3] = t
    return T


def random_pose(rng: np.random.Generator, spread: float = 5.0) -> np.ndarray:
    return rigid(rng.normal(size=4), rng.uniform(-spread, spread, 3))


@pytest.fixture(scope="module")
def design():
    """Blocks at random poses in two stations and parts, a stone slot, a print path,
    a task point, hand-built blocks; stations, anchors, set-ups and as-built poses."""
    rng = np.random.default_rng(7)
    elements = [
        Element(
            f"B{k:03d}",
            "block",
            random_pose(rng),
            layer=k % 3,
            supports=(f"B{k - 1:03d}",) if k else (),
            part="AB"[k % 2],
            robot_built=k < 8,
            extents=np.array([0.6, 0.105, 0.105]) * rng.uniform(0.5, 2.0, 3),
            attributes={"mass": 2.5 + k, "kind": "block"},
        )
        for k in range(12)
    ]
    elements.append(
        Element("S1-slot", "stone", random_pose(rng), extents=np.array([1.6, 1.25, 0.9]))
    )
    s = np.linspace(0.0, 2.0 * np.pi, 50)
    path = np.column_stack([np.cos(s), np.sin(s), 0.01 * s])
    elements.append(
        Element("P000", "print_path", random_pose(rng), polyline=path, attributes={"n": math.nan})
    )
    elements.append(Element("T1", "task_point", random_pose(rng), attributes={"action": "drill"}))
    T_platforms = np.stack([random_pose(rng) for _ in range(2)])
    footprints = platform_footprints(T_platforms, (1.6, 1.2))
    stations = [
        StationRecord("S1", T_platforms[0], footprints[0], ("B000", "B002", "B001", "P000")),
        StationRecord("S2", T_platforms[1], footprints[1], ("B003", "B004", "B005", "T1")),
    ]
    anchors = {"A1": [0.0, 0.0, 1.0], "A2": [4.8, 0.0, 1.0]}
    setups = {"T1": [-2.5, -2.5, 1.6]}
    as_built = {eid: random_pose(rng) for eid in ("B000", "B003", "P000", "T1")}
    return elements, stations, anchors, setups, as_built


@pytest.fixture(scope="module")
def model_3dm(design, tmp_path_factory):
    path = tmp_path_factory.mktemp("rhino") / "plan.3dm"
    write_3dm(path, *design)
    model = rhino3dm.File3dm.Read(str(path))
    layers = [layer.FullPath for layer in model.Layers]
    return model, layers


def objects_on(model, layers, path):
    return [o for o in model.Objects if layers[o.Attributes.LayerIndex] == path]


def vertices(solid) -> np.ndarray:
    """Corners of a box written as an extrusion (or a brep)."""
    brep = solid.ToBrep(True) if isinstance(solid, rhino3dm.Extrusion) else solid
    return np.array([[v.Location.X, v.Location.Y, v.Location.Z] for v in brep.Vertices])


def same_points(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    """Whether two point sets are equal (any order) to ``tol``."""
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    return len(a) == len(b) and d.min(axis=1).max() < tol and d.min(axis=0).max() < tol


def test_3dm_layers_per_station_and_part(design, model_3dm) -> None:
    elements, stations, *_ = design
    model, layers = model_3dm
    assert model.Settings.ModelUnitSystem == rhino3dm.UnitSystem.Meters
    station_of = {eid: s.id for s in stations for eid in s.elements}
    expected = Counter(
        f"fabflow::elements::{station_of.get(e.id, 'unplanned')}::{e.part or 'no_part'}"
        for e in elements
    )
    got = Counter(
        layers[o.Attributes.LayerIndex]
        for o in model.Objects
        if layers[o.Attributes.LayerIndex].startswith("fabflow::elements::")
    )
    assert got == expected
    assert expected["fabflow::elements::S1::A"] == 2 and expected["fabflow::elements::S1::no_part"]
    for name in ("as_built", "stations", "anchors", "setups"):
        assert f"fabflow::{name}" in layers


def test_3dm_elements_carry_their_exact_frame_and_data(design, model_3dm) -> None:
    elements, stations, *_ = design
    model, layers = model_3dm
    station_of = {eid: s.id for s in stations for eid in s.elements}
    objects = {
        o.Attributes.Name: o
        for o in model.Objects
        if layers[o.Attributes.LayerIndex].startswith("fabflow::elements::")
    }
    assert set(objects) == {e.id for e in elements}
    for e in elements:
        o = objects[e.id]
        text = dict(o.Attributes.GetUserStrings())
        T = frame_from_text(text[exchange.KEY_FRAME])
        assert T.tobytes() == np.asarray(e.T_world_element, dtype=float).tobytes()
        assert np.abs(T - e.T_world_element).max() <= 1e-9
        assert text == element_user_text(e, station_of.get(e.id))
        assert text[exchange.KEY_ID] == e.id and text[exchange.KEY_TYPE] == e.type
        assert text[exchange.KEY_ROBOT_BUILT] == ("true" if e.robot_built else "false")
        assert text.get(exchange.KEY_STATION) == station_of.get(e.id)
        assert text.get(exchange.KEY_PART) == e.part
        assert text.get(exchange.KEY_SUPPORTS, "").split(",") == list(e.supports or [""])
        assert json.loads(text[exchange.KEY_ATTRIBUTES]) == {
            k: (None if isinstance(v, float) and math.isnan(v) else v)
            for k, v in e.attributes.items()
        }
        geometry = o.Geometry
        if e.extents is not None:
            assert isinstance(geometry, rhino3dm.Extrusion) and geometry.IsSolid
            corners = box_corners(e.T_world_element[None], e.extents[None])[0]
            assert same_points(vertices(geometry), corners, 1e-9)
            assert json.loads(text[exchange.KEY_EXTENTS]) == e.extents.tolist()
        elif e.polyline is not None:
            assert isinstance(geometry, rhino3dm.PolylineCurve)
            pts = np.array([[p.X, p.Y, p.Z] for p in (geometry.Point(i) for i in range(50))])
            assert np.abs(pts - world_polyline(e)).max() < 1e-9
        else:
            assert isinstance(geometry, rhino3dm.Point)
            p = geometry.Location
            assert np.abs([p.X, p.Y, p.Z] - e.T_world_element[:3, 3]).max() < 1e-12


def test_3dm_stations_anchors_setups_and_as_built(design, model_3dm) -> None:
    elements, stations, anchors, setups, as_built = design
    model, layers = model_3dm
    on_stations = objects_on(model, layers, "fabflow::stations")
    outlines = {
        o.Attributes.Name: o.Geometry for o in on_stations if o.Geometry.ObjectType.name == "Curve"
    }
    dots = {
        o.Attributes.Name: o.Geometry
        for o in on_stations
        if isinstance(o.Geometry, rhino3dm.TextDot)
    }
    assert set(outlines) == set(dots) == {"S1", "S2"}
    for s in stations:
        curve = outlines[s.id]
        assert curve.IsClosed and curve.PointCount == 5
        pts = np.array([[curve.Point(i).X, curve.Point(i).Y, curve.Point(i).Z] for i in range(5)])
        assert np.abs(pts[:4] - s.footprint).max() < 1e-12 and np.array_equal(pts[0], pts[4])
        assert dots[s.id].Text == s.id
    for path, points in (("fabflow::anchors", anchors), ("fabflow::setups", setups)):
        got = {o.Attributes.Name: o.Geometry.Location for o in objects_on(model, layers, path)}
        assert set(got) == set(points)
        for name, p in got.items():
            assert [p.X, p.Y, p.Z] == list(points[name])
    built = {o.Attributes.Name: o for o in objects_on(model, layers, "fabflow::as_built")}
    assert set(built) == set(as_built)
    by_id = {e.id: e for e in elements}
    for eid, o in built.items():
        T = frame_from_text(o.Attributes.GetUserString(exchange.KEY_FRAME))
        assert T.tobytes() == as_built[eid].tobytes()
        e = by_id[eid]
        if e.extents is not None:
            assert same_points(vertices(o.Geometry), box_corners(T[None], e.extents[None])[0], 1e-9)


def test_compas_json_loads_with_the_same_poses(design, tmp_path: Path) -> None:
    elements, stations, anchors, setups, as_built = design
    path = write_compas_json(tmp_path / "plan.json", *design)
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text and "guid" not in text
    doc = compas.json_load(str(path))
    assert doc["fabflow"] == 1 and doc["units"] == "m"
    station_of = {eid: s.id for s in stations for eid in s.elements}
    records = {r["id"]: r for r in doc["elements"]}
    assert list(records) == [e.id for e in elements]
    for e in elements:
        r = records[e.id]
        M = np.array(Transformation.from_frame(r["frame"]).matrix)
        assert np.abs(M - e.T_world_element).max() < 1e-12
        assert r["station"] == station_of.get(e.id) and r["part"] == e.part
        assert r["supports"] == list(e.supports) and r["robot_built"] == e.robot_built
        assert r["type"] == e.type and r["layer"] == e.layer
        g = r["geometry"]
        if e.extents is not None:
            assert [g.xsize, g.ysize, g.zsize] == e.extents.tolist()
            corners = box_corners(e.T_world_element[None], e.extents[None])[0]
            assert same_points(np.array(g.points), corners, 1e-9)
        elif e.polyline is not None:
            assert np.abs(np.array(g.points) - world_polyline(e)).max() < 1e-9
        else:
            assert np.abs(np.array(Transformation.from_frame(g).matrix) - M).max() == 0.0
    assert records["P000"]["attributes"] == {"n": None}
    for s, r in zip(stations, doc["stations"], strict=True):
        assert r["id"] == s.id and r["elements"] == list(s.elements)
        pts = np.array(r["footprint"].points)
        assert len(pts) == 5 and np.array_equal(pts[0], pts[-1])
        assert np.abs(pts[:4] - s.footprint).max() < 1e-12
        M = np.array(Transformation.from_frame(r["frame"]).matrix)
        assert np.abs(M - s.T_world_platform).max() < 1e-12
    assert {a["name"]: list(a["point"]) for a in doc["anchors"]} == anchors
    assert {a["name"]: list(a["point"]) for a in doc["setups"]} == setups
    got = {a["id"]: np.array(Transformation.from_frame(a["frame"]).matrix) for a in doc["as_built"]}
    assert set(got) == set(as_built)
    assert max(np.abs(got[k] - as_built[k]).max() for k in got) < 1e-12


def test_the_same_export_gives_the_same_file(design, tmp_path: Path) -> None:
    a = write_compas_json(tmp_path / "a.json", *design).read_bytes()
    assert a == write_compas_json(tmp_path / "b.json", *design).read_bytes()


@settings(deadline=None, max_examples=200)
@given(quats, st.tuples(coord, coord, coord))
def test_frame_round_trip(q, t) -> None:
    T = rigid(q, t)
    back = frame_from_text(frame_text(T))
    assert back.tobytes() == T.tobytes()  # bit for bit, -0.0 included
    M = np.array(Transformation.from_frame(compas_frame(T)).matrix)
    assert np.abs(M - T).max() < 1e-12


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_poses_are_refused_and_nothing_is_written(design, tmp_path, bad) -> None:
    elements, stations, *_ = design
    T = elements[3].T_world_element.copy()
    T[1, 3] = bad
    broken = [*elements[:3], Element("B003", "block", T, extents=np.ones(3)), *elements[4:]]
    for writer, name in ((write_3dm, "x.3dm"), (write_compas_json, "x.json")):
        target = tmp_path / name
        target.write_text("previous")
        with pytest.raises(InputError, match="element B003: its pose is not finite"):
            writer(target, broken, stations)
        assert target.read_text() == "previous"
        assert sorted(p.name for p in tmp_path.iterdir()) <= ["x.3dm", "x.json"]
    with pytest.raises(InputError, match="as-built element B000: its pose is not finite"):
        export_content(elements, as_built={"B000": np.full((4, 4), np.nan)})


def test_inconsistent_content_is_refused(design) -> None:
    elements, stations, *_ = design
    with pytest.raises(InputError, match="'B000' is used twice"):
        export_content([*elements, elements[0]])
    skew = elements[0].T_world_element.copy()
    skew[:3, :3] *= 1.01
    with pytest.raises(InputError, match="not a rigid transform"):
        export_content([Element("X", "block", skew, extents=np.ones(3))])
    with pytest.raises(InputError, match="builds element 'nope'"):
        export_content(elements, [StationRecord("S9", np.eye(4), np.zeros((4, 3)), ("nope",))])
    two = [stations[0], StationRecord("S3", np.eye(4), np.zeros((4, 3)), ("B000",))]
    with pytest.raises(InputError, match="built from stations S1 and S3"):
        export_content(elements, two)
    with pytest.raises(InputError, match="as-built pose of element 'nope'"):
        export_content(elements, as_built={"nope": np.eye(4)})
    with pytest.raises(InputError, match="anchor A1: its position"):
        export_content(elements, anchors={"A1": [0.0, np.nan, 1.0]})


def test_a_failed_write_leaves_the_previous_file(design, tmp_path, monkeypatch) -> None:
    target = tmp_path / "plan.3dm"
    target.write_bytes(b"previous")
    monkeypatch.setattr(rhino3dm.File3dm, "Write", lambda self, path, version: False)
    with pytest.raises(InputError, match="could not write"):
        write_3dm(target, *design)
    assert target.read_bytes() == b"previous" and [p.name for p in tmp_path.iterdir()] == [
        "plan.3dm"
    ]


def test_missing_libraries_say_what_to_install(design, tmp_path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "rhino3dm", None)
    monkeypatch.setitem(sys.modules, "compas", None)
    with pytest.raises(UnsupportedError, match=r"fabflow\[interop\]"):
        write_3dm(tmp_path / "x.3dm", *design)
    with pytest.raises(UnsupportedError, match=r"fabflow\[interop\]"):
        compas_document(*design)
    assert not list(tmp_path.iterdir())


def test_layer_names_keep_rhinos_separator_out() -> None:
    assert layer_name("front::left") == "front_left"
    assert layer_name(" A\n") == "A_"
    assert layer_name("  ") == "_"
