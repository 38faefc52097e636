"""DXF in (every supported entity type, units, bad drawings) and the site plan DXF out."""

from __future__ import annotations

import math
import warnings

import ezdxf
import numpy as np
import pytest
import shapely
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from fabflow.design.dxf_in import DxfWarning, read_dxf_contours
from fabflow.design.elements import Element
from fabflow.design.generate import task_point_elements
from fabflow.design.site_plan import write_site_plan
from fabflow.design.specs import TaskPoint
from fabflow.errors import InputError
from fabflow.schema import PoseSpec


def _doc(units: int = 4):
    doc = ezdxf.new("R2010", units=units)
    doc.layers.add("PATH")
    return doc, doc.modelspace()


def _read(doc, tmp_path, **kw):
    path = tmp_path / "drawing.dxf"
    doc.saveas(path)
    return read_dxf_contours(path, **kw)


A = {"layer": "PATH"}


def _square_lines(msp, size: float) -> None:
    c = [(0, 0), (size, 0), (size, size), (0, size)]
    for i in range(4):
        msp.add_line(c[i], c[(i + 1) % 4], dxfattribs=A)


def test_lines_chain_into_a_closed_square(tmp_path) -> None:
    doc, msp = _doc()
    _square_lines(msp, 500.0)
    (c,) = _read(doc, tmp_path, layers=["PATH"])
    assert c.closed and len(c.handles) == 4
    assert np.allclose(np.ptp(c.points, axis=0), [0.5, 0.5, 0.0])
    assert np.allclose(c.points[0], c.points[-1])


def test_lwpolyline_with_bulge_is_an_exact_arc(tmp_path) -> None:
    doc, msp = _doc()
    # a stadium: two straight edges and two half circles of radius 100 mm (bulge 1)
    msp.add_lwpolyline(
        [(0, 0, 0, 0, 0), (400, 0, 0, 0, 1), (400, 200, 0, 0, 0), (0, 200, 0, 0, 1)],
        format="xyseb",
        close=True,
        dxfattribs=A,
    )
    (c,) = _read(doc, tmp_path)
    p = c.points[:, :2]
    left = p[:, 0] < 0
    right = p[:, 0] > 0.4
    assert np.allclose(np.linalg.norm(p[left] - [0, 0.1], axis=1), 0.1, atol=1e-9)
    assert np.allclose(np.linalg.norm(p[right] - [0.4, 0.1], axis=1), 0.1, atol=1e-9)
    assert p[:, 0].min() == pytest.approx(-0.1, abs=1e-4)


def test_polyline_2d_and_3d(tmp_path) -> None:
    doc, msp = _doc()
    msp.add_polyline2d([(0, 0), (300, 0), (300, 300)], close=True, dxfattribs=A)
    msp.add_polyline3d([(1000, 0, 50), (1300, 0, 50), (1300, 300, 50)], close=True, dxfattribs=A)
    c2, c3 = _read(doc, tmp_path)
    assert c2.closed and c3.closed
    assert len(c2.points) == 4 and np.allclose(c3.points[:, 2], 0.05)


def test_circle_arc_and_spline(tmp_path) -> None:
    doc, msp = _doc(units=6)  # metres
    msp.add_circle((1.0, 2.0), 0.75, dxfattribs=A)
    msp.add_arc((5.0, 0.0), 1.0, 0.0, 180.0, dxfattribs=A)
    msp.add_line((4.0, 0.0), (6.0, 0.0), dxfattribs=A)
    fit = [(10, 0), (11, 1), (12, 0), (11, -1), (10, 0)]
    msp.add_spline(fit_points=fit, dxfattribs=A)
    circle, arc, spline = _read(doc, tmp_path)
    r = np.linalg.norm(circle.points[:, :2] - [1.0, 2.0], axis=1)
    assert np.allclose(r, 0.75, atol=1e-12) and circle.closed
    assert arc.closed and len(arc.handles) == 2
    on_arc = arc.points[:, 1] > 1e-9
    assert np.allclose(np.linalg.norm(arc.points[on_arc, :2] - [5.0, 0.0], axis=1), 1.0)
    # chord error of the flattened arc is within the flattening tolerance (0.05 mm)
    mid = 0.5 * (arc.points[on_arc][1:] + arc.points[on_arc][:-1])
    assert 1.0 - np.linalg.norm(mid[:, :2] - [5.0, 0.0], axis=1).min() < 5e-5
    assert spline.closed
    for q in fit:
        assert np.linalg.norm(spline.points[:, :2] - q, axis=1).min() < 1e-3


@pytest.mark.parametrize(("code", "scale"), [(4, 1e-3), (5, 1e-2), (6, 1.0), (1, 0.0254)])
def test_insunits_scale(tmp_path, code, scale) -> None:
    doc, msp = _doc(units=code)
    _square_lines(msp, 10.0)
    (c,) = _read(doc, tmp_path)
    assert np.ptp(c.points[:, 0]) == pytest.approx(10.0 * scale)


def test_missing_units_warns_and_reads_millimetres(tmp_path) -> None:
    doc, msp = _doc(units=0)
    _square_lines(msp, 10.0)
    with pytest.warns(DxfWarning, match="INSUNITS"):
        (c,) = _read(doc, tmp_path)
    assert np.ptp(c.points[:, 0]) == pytest.approx(0.01)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (c,) = _read(doc, tmp_path, units="cm")
    assert np.ptp(c.points[:, 0]) == pytest.approx(0.1)


def test_unsupported_entities_are_listed_in_a_warning(tmp_path) -> None:
    doc, msp = _doc()
    _square_lines(msp, 100.0)
    text = msp.add_text("hello", dxfattribs=A)
    msp.add_text("elsewhere", dxfattribs={"layer": "OTHER"})
    with pytest.warns(DxfWarning, match=f"TEXT {text.dxf.handle}") as rec:
        _read(doc, tmp_path, layers=["path"])  # layer names are case-insensitive
    assert "1 unsupported" in str(rec[0].message)


def test_missing_layer_names_the_layer(tmp_path) -> None:
    doc, msp = _doc()
    _square_lines(msp, 100.0)
    with pytest.raises(InputError, match="no layer 'WALL'") as err:
        _read(doc, tmp_path, layers=["WALL"])
    assert "PATH" in str(err.value) and err.value.location == "layer WALL"
    doc.layers.add("EMPTY")
    with pytest.raises(InputError, match="layer 'EMPTY' holds no"):
        _read(doc, tmp_path, layers=["EMPTY"])


def test_open_contour_where_closed_is_required(tmp_path) -> None:
    doc, msp = _doc()
    line = msp.add_line((0, 0), (100, 0), dxfattribs=A)
    msp.add_line((100, 0), (100, 100), dxfattribs=A)
    with pytest.raises(InputError, match="open contour") as err:
        _read(doc, tmp_path)
    assert line.dxf.handle in str(err.value)
    (c,) = _read(doc, tmp_path, require_closed=False)
    assert not c.closed and len(c.points) == 3


def test_zero_length_segments_name_the_entity(tmp_path) -> None:
    doc, msp = _doc()
    bad = msp.add_line((5, 5), (5, 5), dxfattribs=A)
    with pytest.raises(InputError, match="zero-length") as err:
        _read(doc, tmp_path)
    assert err.value.location == f"entity {bad.dxf.handle}"
    doc, msp = _doc()
    bad = msp.add_lwpolyline([(0, 0), (10, 0), (10, 0), (10, 10)], close=True, dxfattribs=A)
    with pytest.raises(InputError, match="vertices 1 and 2") as err:
        _read(doc, tmp_path)
    assert err.value.location == f"entity {bad.dxf.handle}"
    doc, msp = _doc()
    bad = msp.add_circle((0, 0), 0.0, dxfattribs=A)
    with pytest.raises(InputError, match="zero radius"):
        _read(doc, tmp_path)


def test_self_intersection_names_the_entities(tmp_path) -> None:
    doc, msp = _doc()
    bow = msp.add_lwpolyline([(0, 0), (100, 100), (100, 0), (0, 100)], close=True, dxfattribs=A)
    with pytest.raises(InputError, match="crosses itself near") as err:
        _read(doc, tmp_path)
    assert bow.dxf.handle in str(err.value)


def test_not_a_dxf(tmp_path) -> None:
    path = tmp_path / "x.dxf"
    path.write_text("this is not a drawing\n")
    with pytest.raises(InputError, match=r"not a valid DXF|cannot read"):
        read_dxf_contours(path)


def test_site_plan_round_trip(tmp_path) -> None:
    """Elements -> site plan DXF -> read back: the print path comes back in metres."""
    th = np.linspace(0, 2 * np.pi, 73)
    ring = np.column_stack([np.cos(th), np.sin(th), np.zeros_like(th)])
    ring[-1] = ring[0]
    T = np.eye(4)
    T[:3, 3] = [2.0, 3.0, 0.02]
    path_el = Element(
        id="P000",
        type="print_path",
        T_world_element=T,
        polyline=ring,
        attributes={"extrude": [True] * 72},
    )
    block = Element(
        id="B0000",
        type="block",
        T_world_element=np.eye(4),
        extents=np.array([0.6, 0.105, 0.105]),
        part="A",
    )
    tp = task_point_elements([TaskPoint(id="t1", pose=PoseSpec(xyz=(1.0, 1.0, 0.0)))])
    stations = [
        {"id": "S1", "T_world_platform": np.eye(4)},
        {"id": "S2", "T_world_platform": T},
    ]
    out = write_site_plan(
        tmp_path / "plan.dxf",
        [path_el, block, *tp],
        stations=stations,
        platform_footprint=(2.2, 1.6),
        anchors={"A1": (0.0, 0.0, 1.0), "A2": (4.8, 0.0, 1.0)},
        instrument=np.eye(4),
    )
    doc = ezdxf.readfile(out)
    assert not doc.audit().has_errors
    assert doc.header["$INSUNITS"] == 4
    layers = {e.dxf.layer for e in doc.modelspace()}
    assert {
        "FOOTPRINT",
        "PART_A",
        "PRINT_PATH",
        "TASK_POINTS",
        "STATIONS",
        "PLATFORMS",
        "UWB_ANCHORS",
        "TOTAL_STATION",
    } <= layers
    (back,) = read_dxf_contours(out, layers=["PRINT_PATH"])
    assert back.closed
    assert np.allclose(back.points, ring + T[:3, 3], atol=1e-9)
    (fp,) = read_dxf_contours(out, layers=["FOOTPRINT"])
    assert np.allclose(np.ptp(fp.points[:, :2], axis=0), [0.6, 0.105])
    platforms = read_dxf_contours(out, layers=["PLATFORMS"])
    assert len(platforms) == 2
    assert math.isclose(np.ptp(platforms[0].points[:, 0]), 2.2)


def test_cli_build_reports_a_missing_layer(cli, tmp_path) -> None:
    doc, msp = _doc()
    _square_lines(msp, 100.0)
    doc.saveas(tmp_path / "wall.dxf")
    (tmp_path / "project.yaml").write_text(
        "name: bad\nelements:\n  - print_path: {dxf: wall.dxf, layers: [WALL]}\n"
    )
    result = cli("build", str(tmp_path), "-o", str(tmp_path / "out"))
    assert result.returncode == 2
    assert "wall.dxf" in result.stderr and "layer WALL" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "out").exists()


def test_implausible_size_warns_about_units(tmp_path) -> None:
    doc, msp = _doc(units=6)  # a drawing in millimetres marked as metres
    _square_lines(msp, 4000.0)
    with pytest.warns(DxfWarning, match="check the drawing units"):
        _read(doc, tmp_path)


@settings(deadline=None, max_examples=25)
@given(
    st.lists(
        st.tuples(st.integers(-5000, 5000), st.integers(-5000, 5000)),
        min_size=2,
        max_size=12,
        unique=True,
    )
)
def test_lwpolyline_round_trip(tmp_path_factory, xy) -> None:
    """Any open LWPOLYLINE (mm) comes back as its vertices in metres."""
    pts = np.array(xy, dtype=float)
    segs = shapely.linestrings(np.stack([pts[:-1], pts[1:]], axis=1))
    # only simple paths are valid input
    i, j = shapely.STRtree(segs).query(segs, predicate="intersects")
    assume(not np.any(j > i + 1))
    doc, msp = _doc()
    msp.add_lwpolyline(pts.tolist(), dxfattribs=A)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DxfWarning)  # tiny drawings warn about units
        (c,) = _read(doc, tmp_path_factory.mktemp("rt"), require_closed=False)
    assert np.allclose(c.points[:, :2], pts / 1000.0)
    assert not c.closed
